"""rosbag2 (MCAP) bags: message types and QoS, a crash-tolerant writer and reader, recovery.

Shared by the tools (make_bag, evaluate, demo, maem-bag) and the nodes (player, recorder), so all
use one format; no rclpy needed. Message layouts live in maem_ros/wire: a writer takes either a
``rosbags`` message (serialised with the ROS 2 Jazzy typestore; maem_ros.wire builds them) or
an rclpy message built by ros/wire (serialised by rclpy, which needs no init). Reading returns
CDR bytes and ``rosbags`` messages, which the wire's decoders accept as they are. Stamps are
integer nanoseconds everywhere.

Modules: messages (typestore, QoS, CDR), metadata (metadata.yaml), mcapfile (one MCAP file,
whole or cut short), writer (BagWriter: bounded chunks, splitting, full disk), reader (opening a
bag tolerantly: the one place that decides what damage is read through), recover (maem-bag).
"""

from __future__ import annotations

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime  # noqa: F401

from maem_ros.bagio.messages import (  # noqa: F401
    CAMERA_INFO,
    CLOCK,
    COMPRESSED_IMAGE,
    GT_TOPIC,
    IMAGE,
    POINT_CLOUD2,
    QOS_LATCHED,
    QOS_RELIABLE,
    QOS_SENSOR,
    SCENE_TOPIC,
    STRING,
    TYPESTORE,
    clock_msg,
    deserialize,
    is_image_type,
    known_type,
    msgtype_of,
    serialize,
    stamp_to_ns,
    string_msg,
    time_msg,
)
from maem_ros.bagio.metadata import BagError  # noqa: F401
from maem_ros.bagio.reader import (  # noqa: F401
    CUSTOM_GT_CONVENTION,
    CUSTOM_RIG,
    CUSTOM_SCENE,
    BagInfo,
    BagMessage,
    custom_data,
    read_messages,
    read_rig_yaml,
    read_scene,
    read_scene_config,
)
from maem_ros.bagio.reader import open_info as bag_info  # noqa: F401
from maem_ros.bagio.writer import BagWriteError, BagWriter, WriteOptions  # noqa: F401
