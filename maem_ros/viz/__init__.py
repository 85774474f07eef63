"""Live visualisation without ROS: Foxglove messages (scene.py) and the WebSocket bridge
(bridge.py) on the foxglove-sdk package. Used by the live node (ros/foxglove_node.py) and the bag
source (tools/export/foxglove_view.py); imports neither rclpy nor tools/ nor sim/."""
