"""ROS 2 message types for bags: the Jazzy typestore, recorded QoS profiles, CDR
(de)serialisation of rosbags and rclpy messages. No rclpy import (rclpy messages are serialised
by rclpy only when given one)."""

from __future__ import annotations

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types

#: topic carrying the synthetic scene description (std_msgs/String JSON, transient local)
SCENE_TOPIC = "/maem/scene"
#: topic carrying ground-truth poses (PointCloud2, Poses layout)
GT_TOPIC = "/maem/gt_poses"
#: metadata.yaml custom_data keys
CUSTOM_SCENE = "maem.scene"
CUSTOM_RIG = "maem.rig"
CUSTOM_GT_CONVENTION = "maem.gt_convention"

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
STRING = "std_msgs/msg/String"
CLOCK = "rosgraph_msgs/msg/Clock"


# ---- QoS (as recorded in metadata offered_qos_profiles) -----------------------------------------
def _qos(reliability: QosReliability, durability: QosDurability, depth: int) -> Qos:
    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST, depth, reliability, durability, zero, zero, QosLiveliness.AUTOMATIC, zero, False
    )


QOS_SENSOR = _qos(QosReliability.BEST_EFFORT, QosDurability.VOLATILE, 5)
QOS_RELIABLE = _qos(QosReliability.RELIABLE, QosDurability.VOLATILE, 10)
QOS_LATCHED = _qos(QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)


def is_image_type(msgtype: str) -> bool:
    return msgtype in (IMAGE, COMPRESSED_IMAGE)


# ---- small standard messages (rosbags) ------------------------------------------------------------
def time_msg(stamp_ns: int):
    """builtin_interfaces/Time from integer nanoseconds (>= 0)."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f"stamp: {stamp_ns} ns is negative")
    return _T["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time (any object with sec, nanosec) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def string_msg(text: str):
    return _T[STRING](data=text)


def clock_msg(stamp_ns: int):
    return _T[CLOCK](clock=time_msg(stamp_ns))


# ---- serialisation ---------------------------------------------------------------------------------
def msgtype_of(msg) -> str:
    """``pkg/msg/Name`` of a rosbags or an rclpy message."""
    if hasattr(msg, "__msgtype__"):
        return msg.__msgtype__
    return f"{type(msg).__module__.split('.', 1)[0]}/msg/{type(msg).__name__}"


def serialize(msg) -> bytes:
    """CDR bytes of a rosbags message or an rclpy message (e.g. from ros/wire)."""
    if hasattr(msg, "__msgtype__"):
        return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    from rclpy.serialization import serialize_message

    return bytes(serialize_message(msg))


def deserialize(data: bytes | memoryview, msgtype: str):
    return TYPESTORE.deserialize_cdr(data, msgtype)


def known_type(msgtype: str) -> bool:
    return msgtype in _T


def schema_text(msgtype: str) -> tuple[str, str]:
    """(ros2msg definition text, RIHS01 type hash) of a typestore type, as rosbag2 stores them
    in an MCAP Schema record and in metadata.yaml."""
    msgdef, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
    return msgdef, TYPESTORE.hash_rihs01(msgtype)
