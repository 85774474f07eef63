"""maem_ros: Mesh-Aware Epipolar Matching as a ROS 2 node graph."""
