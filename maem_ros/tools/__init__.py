"""The command-line tools (console scripts in setup.cfg), grouped by what a user does with them.

- ``demo/``: maem-demo (the demo bag through the node graph) and maem-pose2sim-demo (real footage);
- ``bench/``: maem-bench (association / triangulation timing, ``--live`` through the graph),
  maem-soak, and the graph latency replay;
- ``bags/``: maem-bag (inspect, recover), maem-make-bag, maem-record-faults;
- ``eval/``: maem-eval (offline scoring of a scene folder), its loss breakdown and plots;
- ``export/``: maem-export (TRC, C3D, CSV) and maem-foxglove (a live Foxglove view);
- ``calibrate/``: maem-calibrate (people, board), its report and maem-calib-bench;
- ``simulate`` (maem-sim), ``warmup`` (maem-warmup), ``paramdoc`` (the parameter tables),
  ``processes`` (child processes of the graph tools).
"""
