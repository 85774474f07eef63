"""rosbag2 (MCAP) reading and writing on ``rosbags``: typestore, QoS, writer, reader.

Shared by the tools (make_bag, evaluate, demo) and the nodes (player, recorder), so both use one
format. Message layouts live in ros/wire.py: a writer takes either a ``rosbags`` message
(serialised with the ROS 2 Jazzy typestore) or an rclpy message built by wire.py (serialised by
rclpy, which needs no init). Reading returns CDR bytes and ``rosbags`` messages, which wire.py's
decoders accept as they are. Stamps are integer nanoseconds everywhere.
"""
from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

from maem_ros.core.errors import InputError

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
    return Qos(QosHistory.KEEP_LAST, depth, reliability, durability, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


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
    return _T["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                             nanosec=stamp_ns % 1_000_000_000)


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
    """CDR bytes of a rosbags message or an rclpy message (e.g. from ros/wire.py)."""
    if hasattr(msg, "__msgtype__"):
        return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    from rclpy.serialization import serialize_message
    return bytes(serialize_message(msg))


def deserialize(data: bytes, msgtype: str):
    return TYPESTORE.deserialize_cdr(data, msgtype)


def known_type(msgtype: str) -> bool:
    return msgtype in _T


# ---- writing ---------------------------------------------------------------------------------------
class BagWriter:
    """rosbag2 MCAP writer: topics registered on first use; ``close()`` writes metadata.yaml.

    ``compress`` enables zstd MCAP chunk compression (storage compression).
    """

    def __init__(self, path: str | Path, compress: bool = False):
        self.path = Path(path)
        self._writer = Writer(self.path, version=Writer.VERSION_LATEST,
                              storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self._writer.open()
        self._open = True

    def add_topic(self, topic: str, msgtype: str, qos: Qos | None = None) -> None:
        """Register a topic (no-op if already registered with the same type)."""
        if topic in self._conns:
            if self._conns[topic].msgtype != msgtype:
                raise ValueError(f"topic {topic!r}: already registered as {self._conns[topic].msgtype}, "
                                 f"not {msgtype}")
            return
        if not known_type(msgtype):
            raise ValueError(f"topic {topic!r}: message type {msgtype!r} is not in the ROS 2 Jazzy "
                             "typestore")
        if qos is None:
            qos = QOS_SENSOR if is_image_type(msgtype) else QOS_RELIABLE
        self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=TYPESTORE,
                                                         offered_qos_profiles=[qos])
        self.counts[topic] = 0

    def write(self, topic: str, msg, stamp_ns: int, qos: Qos | None = None) -> None:
        """Serialise and write a rosbags or rclpy message at log time ``stamp_ns``."""
        self.write_raw(topic, msgtype_of(msg), serialize(msg), stamp_ns, qos)

    def write_raw(self, topic: str, msgtype: str, data: bytes, stamp_ns: int,
                  qos: Qos | None = None) -> None:
        """Write already-serialised CDR bytes."""
        self.add_topic(topic, msgtype, qos)
        self._writer.write(self._conns[topic], int(stamp_ns), data)
        self.counts[topic] += 1

    def set_custom(self, key: str, value: str) -> None:
        """metadata.yaml custom_data entry (string value)."""
        self._writer.set_custom_data(key, value)

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def close(self) -> None:
        if self._open:
            self._open = False
            self._writer.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- reading ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes

    def decode(self):
        return deserialize(self.data, self.msgtype)


@dataclass
class BagInfo:
    topics: dict[str, str]  # topic -> msgtype
    counts: dict[str, int]
    start_ns: int
    end_ns: int  # last message log time (inclusive)
    message_count: int
    custom: dict[str, str]
    qos: dict[str, list[Qos]]  # topic -> offered QoS profiles recorded


class BagError(InputError):
    """A bag that cannot be read: ``bag '<path>': <problem>`` on one line."""

    reason = "bad_bag"


def _check_bag(path: Path) -> Path:
    if not path.exists():
        raise BagError(f"bag {str(path)!r}: not a rosbag2 folder (no such file or directory)")
    if not (path / "metadata.yaml").is_file():
        raise BagError(f"bag {str(path)!r}: not a rosbag2 folder (no metadata.yaml)")
    return path


@contextmanager
def _reading(path: Path) -> Iterator[None]:
    """rosbags / YAML / OS errors of a damaged bag (zero-byte or truncated mcap, garbage
    metadata.yaml, missing storage file) as one-line BagErrors."""
    try:
        yield
    except BagError:
        raise
    except (ReaderError, yaml.YAMLError, OSError, KeyError, TypeError, ValueError,
            AttributeError, IndexError, struct.error) as e:
        problem = " ".join(str(e).split()) or type(e).__name__
        raise BagError(f"bag {str(path)!r}: unreadable ({type(e).__name__}: "
                       f"{problem[:200]})") from None


def bag_info(path: str | Path) -> BagInfo:
    """Topics, counts, time range, custom data and recorded QoS of a rosbag2 folder."""
    path = _check_bag(Path(path))
    with _reading(path), Reader(path) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        counts = {t: 0 for t in topics}
        qos: dict[str, list[Qos]] = {}
        for c in reader.connections:
            counts[c.topic] += c.msgcount
            qos.setdefault(c.topic, list(getattr(c.ext, "offered_qos_profiles", []) or []))
        n = reader.message_count
        start, end = (reader.start_time, reader.end_time - 1) if n else (0, 0)
    return BagInfo(topics, counts, start, end, n, custom_data(path), qos)


def custom_data(path: str | Path) -> dict[str, str]:
    """metadata.yaml custom_data (empty dict when absent)."""
    path = _check_bag(Path(path))
    with _reading(path):
        meta = yaml.safe_load((path / "metadata.yaml").read_text()) or {}
        return dict(meta.get("rosbag2_bagfile_information", {}).get("custom_data") or {})


def read_messages(path: str | Path, topics: Iterable[str] | None = None,
                  start_ns: int | None = None, stop_ns: int | None = None) -> Iterator[BagMessage]:
    """Messages in log-time order, optionally only ``topics`` and log times in [start, stop)."""
    path = _check_bag(Path(path))
    wanted = None if topics is None else set(topics)
    with _reading(path), Reader(path) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        for conn, t, data in reader.messages(connections=conns, start=start_ns, stop=stop_ns):
            yield BagMessage(conn.topic, conn.msgtype, int(t), bytes(data))


def read_scene(path: str | Path) -> dict | None:
    """The scene description recorded by make_bag (custom data, else the /maem/scene message)."""
    custom = custom_data(path)
    if CUSTOM_SCENE in custom:
        return json.loads(custom[CUSTOM_SCENE])
    for msg in read_messages(path, [SCENE_TOPIC]):
        return json.loads(msg.decode().data)
    return None


def read_scene_config(path: str | Path) -> dict | None:
    """The simulator's SceneConfig dict (scene.json ``scene_config``) recorded in a bag, or None.

    This is what the synthetic frontend backend takes as ``scene_dict`` (as JSON).
    """
    scene = read_scene(path)
    return None if scene is None else scene.get("scene_config")


def read_rig_yaml(path: str | Path) -> str | None:
    """Rig YAML text recorded by make_bag in custom data (None if absent)."""
    return custom_data(path).get(CUSTOM_RIG)
