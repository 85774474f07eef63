"""CDR bytes <-> messages, without rclpy: the rosbags typestore of bagio (ROS 2 Jazzy).

Why rosbags and no codec of our own: rosbags (a maintained library) generates its CDR
(de)serialisers from the message definitions, the same the bags are written with (bagio), so a
message decoded here is the one rclpy or a bag reader would see; and on a memoryview it slices
a uint8[] payload without copying it, which rclpy's own deserialisation does not (it converts
the payload element by element: for six 1.8 MB full-mesh detections messages a frame, more
than the association itself costs).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.wire.cloud import Cloud, WireError, split_stamp

_T = bagio.TYPESTORE.types


def cdr_header_stamp_ns(data: bytes) -> int:
    """Header stamp of a serialized message whose first field is std_msgs/Header (CDR: 4-byte
    encapsulation header, then builtin_interfaces/Time sec int32, nanosec uint32), without
    deserialising the rest."""
    if len(data) < 12:
        raise ValueError(f"serialized message: {len(data)} bytes, too short for a header")
    endian = "<" if data[1] & 1 else ">"
    sec, nsec = struct.unpack_from(endian + "iI", data, 4)
    return sec * 1_000_000_000 + nsec


def cdr_to_cloud(data: bytes | np.ndarray, topic: str) -> Any:
    """A serialized sensor_msgs/PointCloud2 (CDR, what a raw subscription takes or a bag holds)
    -> a rosbags message the decoders here read, its ``data`` a numpy view into ``data`` (no
    copy; ``data`` bytes, or a uint8 array as ros.raw_take takes it). WireError (reason
    ``bad_cdr``) for bytes that are no PointCloud2."""
    try:
        # a memoryview: rosbags slices it for the uint8[] payload (a bytes slice would copy)
        view = data.data if isinstance(data, np.ndarray) else memoryview(data)
        return bagio.deserialize(view, bagio.POINT_CLOUD2)
    except Exception as e:  # noqa: BLE001 - any decoder failure is the same bad input
        raise WireError(
            topic,
            "data",
            f"not a serialized PointCloud2 ({len(data)} bytes: {type(e).__name__}: {e})",
            "bad_cdr",
        ) from None


def ns_to_stamp(ns: int) -> Any:
    """Integer nanoseconds (0 .. MAX_STAMP_NS) -> rosbags builtin_interfaces/Time."""
    sec, nsec = split_stamp(ns)
    return _T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)


def make_header(stamp_ns: int, frame_id: str) -> Any:
    """rosbags std_msgs/Header."""
    return _T["std_msgs/msg/Header"](stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def to_rosbags(cloud: Cloud) -> Any:
    """A :class:`Cloud` -> rosbags sensor_msgs/PointCloud2 (its data a view of the cloud's
    buffer), which bagio writes and the decoders read."""
    pf = _T["sensor_msgs/msg/PointField"]
    h = cloud.header
    return _T[bagio.POINT_CLOUD2](
        header=_T["std_msgs/msg/Header"](
            stamp=_T["builtin_interfaces/msg/Time"](sec=h.stamp.sec, nanosec=h.stamp.nanosec),
            frame_id=h.frame_id,
        ),
        height=cloud.height,
        width=cloud.width,
        fields=[pf(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in cloud.fields],
        is_bigendian=cloud.is_bigendian,
        point_step=cloud.point_step,
        row_step=cloud.row_step,
        data=np.frombuffer(cloud.data, dtype=np.uint8),
        is_dense=cloud.is_dense,
    )
