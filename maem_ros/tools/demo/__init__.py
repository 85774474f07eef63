"""maem-demo (``demo``: the demo bag replayed through the real node graph, ``demo_graph``: its
processes and replay; ``demo_bag``, ``demo_report``, ``demo_metrics``: its bag, report and
ground-truth-free measures) and maem-pose2sim-demo (``pose2sim_demo``: Pose2Sim's real
multi-person capture end to end)."""
