"""Every use of rclpy in the project: the nodes and what they share.

Nodes (console scripts in setup.cfg; thin: parameters -> wire -> core -> publish; all but the
player and recorder on the ``MaemNode`` base):
``frontend_node`` (image -> detections, MAEM stage 1), ``association_node`` (detections of
every camera -> clusters, stage 2), ``triangulation_node`` (clusters -> poses and skeleton
markers, stage 3), ``camera_node`` (video/image folder -> images), ``player_node`` /
``recorder_node`` (MCAP bags), ``foxglove_node`` (live Foxglove view).

Shared: ``node`` (the MaemNode base: parameters, diagnostics, errors, shutdown), ``params``
(parameter declaration from core.paramspec, rig loading), ``qos``, ``diagnostics``,
``intake`` (counted subscriptions, taking what is pending), ``raw_take`` (serialized samples
taken by librcl into arrays, and the executor that does it), ``overload`` (the backlog policy on a node),
``process`` (DDS profile, executor, run_node), ``rig_tf``, ``cli`` (--help), ``fastdds`` (a
guard against a Fast DDS teardown deadlock), ``probe`` (in-process graph probes for the
tools), ``wire`` (rclpy messages from the codec in maem_ros.wire).
"""
