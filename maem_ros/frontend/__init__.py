"""MAEM stage 1 backends: one camera's image (or stamp) -> FrameDetections in rectified px.

``base.make_estimator(backend, options, rig)`` picks one: ``sam3d_body`` (the official SAM 3D
Body model), ``mediapipe`` (BlazePose, CPU), ``npz`` (precomputed SAM 3D Body outputs),
``synthetic`` (the simulator's noise model). ``rectify`` undistorts raw images into the rig's
rectified pinhole image; ``overlay`` draws detections for debugging. No rclpy: the frontend
node (maem_ros.ros.frontend_node) wraps them.
"""
