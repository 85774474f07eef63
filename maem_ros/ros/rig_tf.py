"""The rig's camera frames on /tf_static."""

from __future__ import annotations

from rclpy.node import Node

from maem_ros.ros.qos import TF_STATIC_QOS


def publish_rig_tf(node: Node, rig, world_frame: str):
    """Publish world -> every rig camera once on /tf_static (transient local, so late joiners
    get it); the publisher, or None with one log line when tf2_msgs is not importable (it is
    built by ``make``, see doc/design.md §4)."""
    from maem_ros.core.geometry.frames import rig_transforms
    from maem_ros.ros import wire

    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        node.get_logger().warning(
            "TF skipped: tf2_msgs is not importable (make builds it from "
            "its upstream definition; see doc/design.md §4)"
        )
        return None
    pub = node.create_publisher(TFMessage, wire.TF_STATIC_TOPIC, TF_STATIC_QOS)
    pub.publish(wire.tf_message(rig_transforms(rig, world_frame), node.get_clock().now().nanoseconds))
    return pub
