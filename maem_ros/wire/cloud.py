"""PointCloud2 as a structured numpy array: packed layouts for encoding, validated zero-copy views
for decoding, and the message-shaped :class:`Cloud` the encoders fill. No rclpy.

A decoder here reads any object shaped like sensor_msgs/PointCloud2 (``header.stamp.sec``,
``header.frame_id``, ``fields[i].name/offset/datatype/count``, ``height``, ``width``,
``is_bigendian``, ``point_step``, ``row_step``, ``data``): an rclpy message, a rosbags message
read from a bag, or a :class:`Cloud`.
"""

from __future__ import annotations

import array
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from maem_ros.core.errors import InputError

#: sensor_msgs/PointField datatype codes (fixed by the message definition)
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
F32, U32, U16, U8 = FLOAT32, UINT32, UINT16, UINT8
_NP_OF_PF = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "i2",
    UINT16: "u2",
    INT32: "i4",
    UINT32: "u4",
    FLOAT32: "f4",
    FLOAT64: "f8",
}
_PF_NAME = {
    INT8: "INT8",
    UINT8: "UINT8",
    INT16: "INT16",
    UINT16: "UINT16",
    INT32: "INT32",
    UINT32: "UINT32",
    FLOAT32: "FLOAT32",
    FLOAT64: "FLOAT64",
}

#: builtin_interfaces/Time.sec is int32: stamps from 0 up to 2^31 s (2038-01-19) fit
MAX_STAMP_NS = 2**31 * 1_000_000_000 - 1


class WireError(InputError):
    """A message that cannot be decoded: ``topic: field: problem`` plus a diagnostics reason."""

    def __init__(self, topic: str, field: str, problem: str, reason: str):
        super().__init__(f"{topic}: {field}: {problem}", reason)
        self.topic, self.field, self.problem = topic, field, problem


# ---------------------------------------------------------------------------------------------
# stamps
# ---------------------------------------------------------------------------------------------
def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (any object with sec, nanosec) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def checked_stamp_ns(stamp: Any, topic: str) -> int:
    """stamp_to_ns for a received header: WireError (reason bad_stamp) for a negative sec or a
    nanosec outside 0..999,999,999, which would otherwise decode to a wrong instant."""
    if stamp.sec < 0 or not 0 <= stamp.nanosec < 1_000_000_000:
        raise WireError(
            topic, "header.stamp", f"invalid stamp sec={stamp.sec} nanosec={stamp.nanosec}", "bad_stamp"
        )
    return stamp_to_ns(stamp)


def split_stamp(ns: int) -> tuple[int, int]:
    """Integer nanoseconds (0 .. MAX_STAMP_NS) -> (sec, nanosec); ValueError outside."""
    if not 0 <= int(ns) <= MAX_STAMP_NS:
        raise ValueError(f"stamp: {int(ns)} ns is outside builtin_interfaces/Time (0 .. 2^31 s)")
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return sec, nsec


# ---------------------------------------------------------------------------------------------
# the message-shaped cloud the encoders fill
# ---------------------------------------------------------------------------------------------
@dataclass
class Time:
    """builtin_interfaces/Time."""

    sec: int = 0
    nanosec: int = 0


@dataclass
class Header:
    """std_msgs/Header."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class PointField:
    """sensor_msgs/PointField (offset in bytes within a point, datatype a code above)."""

    name: str
    offset: int
    datatype: int
    count: int


@dataclass
class Cloud:
    """sensor_msgs/PointCloud2 in plain Python (height 1, little-endian, dense): what the
    encoders build and the decoders read; ``data`` is the byte buffer (array.array 'B'), which
    the ROS adapters (ros/wire) and :func:`maem_ros.wire.cdr.to_rosbags` attach without copy."""

    header: Header
    fields: list[PointField]
    width: int
    point_step: int
    data: Any
    height: int = 1
    is_bigendian: bool = False
    is_dense: bool = True

    @property
    def row_step(self) -> int:
        return self.width * self.point_step


def packed_dtype(fields: Sequence[tuple[str, int, int]]) -> np.dtype:
    """Packed little-endian structured dtype for [(name, PointField datatype, count)]."""
    names, formats, offsets, off = [], [], [], 0
    for name, dt, count in fields:
        base = np.dtype("<" + _NP_OF_PF[dt])
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(off)
        off += base.itemsize * count
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})


def new_cloud(
    stamp_ns: int, frame_id: str, fields: Sequence[tuple[str, int, int]], n: int
) -> tuple[Cloud, np.ndarray]:
    """An n-point Cloud and a writable structured (n,) view of its zeroed data buffer: fill
    the view, and the cloud carries the values (no copy)."""
    dtype = packed_dtype(fields)
    offsets = {name: dtype.fields[name][1] for name in dtype.names or ()}  # type: ignore[index]  # fields set: a record dtype
    sec, nsec = split_stamp(stamp_ns)
    buf = array.array("B", bytes(n * dtype.itemsize))
    cloud = Cloud(
        header=Header(Time(sec, nsec), frame_id),
        fields=[PointField(name, offsets[name], dt, count) for name, dt, count in fields],
        width=n,
        point_step=dtype.itemsize,
        data=buf,
    )
    return cloud, np.frombuffer(buf, dtype=dtype, count=n)


# ---------------------------------------------------------------------------------------------
# decoding
# ---------------------------------------------------------------------------------------------
def _layout(msg: Any, topic: str, expected: Mapping[str, int]) -> tuple[dict[str, Any], int]:
    """The fields of ``msg`` by name, each known, listed once, every expected one present."""
    seen: dict[str, Any] = {}
    for f in msg.fields:
        label = f.name or "''"
        if f.name in seen:
            raise WireError(topic, label, "field listed twice", "duplicate_field")
        if f.name not in expected:
            raise WireError(topic, label, f"unknown field (expected {sorted(expected)})", "unknown_field")
        seen[f.name] = f
    missing = [k for k in expected if k not in seen]
    if missing:
        raise WireError(topic, missing[0], f"missing field (got {sorted(seen)})", "missing_field")
    return seen, int(msg.point_step)


def _check_sizes(msg: Any, topic: str, step: int) -> int:
    """Number of points; WireError when point_step, row_step or the data length disagree."""
    n = int(msg.width) * int(msg.height)
    if n and step <= 0:
        raise WireError(topic, "point_step", f"{step} with {n} points", "bad_size")
    if int(msg.height) > 1 and int(msg.row_step) != int(msg.width) * step:
        raise WireError(
            topic, "row_step", f"{msg.row_step} != width {msg.width} x point_step {step}", "bad_size"
        )
    if int(msg.height) <= 1 and n and int(msg.row_step) != n * step:
        raise WireError(
            topic, "row_step", f"{msg.row_step} != width {msg.width} x point_step {step}", "bad_size"
        )
    if len(msg.data) != n * step:
        raise WireError(
            topic, "data", f"{len(msg.data)} bytes, expected {n} points x {step} bytes", "bad_size"
        )
    return n


def view_cloud(
    msg: Any, topic: str, expected: Mapping[str, int], optional: Mapping[str, int] | None = None
) -> np.ndarray:
    """Validate layout and return a structured (N,) view of msg.data (zero-copy).

    ``expected`` maps every required field name to its PointField datatype, ``optional`` the
    fields that may be absent; any other field is an error. Each field's count is returned as
    the subarray length (count 1 -> shape (N,1)).
    """
    present = {k: v for k, v in (optional or {}).items() if any(f.name == k for f in msg.fields)}
    expected = {**expected, **present}
    seen, step = _layout(msg, topic, expected)
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets, spans = [], [], [], []
    for name, dt in expected.items():
        f = seen[name]
        if f.datatype != dt:
            raise WireError(
                topic,
                name,
                f"datatype {_PF_NAME.get(f.datatype, f.datatype)}, expected {_PF_NAME[dt]}",
                "bad_datatype",
            )
        base = np.dtype(endian + _NP_OF_PF[dt])
        size = base.itemsize * int(f.count)
        if f.offset + size > step:
            raise WireError(
                topic, name, f"offset {f.offset} + {size} bytes exceeds point_step {step}", "bad_layout"
            )
        names.append(name)
        formats.append((base, (int(f.count),)))
        offsets.append(int(f.offset))
        spans.append((int(f.offset), int(f.offset) + size, name))
    spans.sort()
    for (_a0, a1, an), (b0, _, bn) in zip(spans, spans[1:]):
        if b0 < a1:
            raise WireError(topic, bn, f"overlaps field {an!r}", "bad_layout")
    n = _check_sizes(msg, topic, step)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": max(step, 1)})
    if n == 0:
        return np.zeros(0, dtype=dtype)
    return np.frombuffer(msg.data, dtype=dtype, count=n)


def field_of(rec: np.ndarray, name: str) -> np.ndarray:
    """(N, count) view of one field in native byte order (copy only for big-endian data)."""
    arr = rec[name]
    return arr if arr.dtype.isnative else arr.astype(arr.dtype.newbyteorder("="))


def count_of(msg: Any, name: str) -> int:
    """The PointField count of field ``name`` of ``msg``."""
    return next(int(f.count) for f in msg.fields if f.name == name)


def check_count(msg: Any, topic: str, name: str, expected: int, what: str = "") -> None:
    """WireError (bad_count) unless field ``name`` has count ``expected``."""
    got = count_of(msg, name)
    if got != expected:
        raise WireError(topic, name, f"count {got}, expected {expected}{what}", "bad_count")


def check_finite(
    topic: str, name: str, arr: np.ndarray, what: str = "detection", allow_nan: bool = False
) -> None:
    """WireError (nonfinite) naming the first row with inf (or NaN unless ``allow_nan``)."""
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        row = int(np.argwhere(bad.reshape(len(arr), -1).any(axis=1))[0][0])
        raise WireError(topic, name, f"{'inf' if allow_nan else 'NaN or inf'} in {what} {row}", "nonfinite")


def check_score(topic: str, scores: np.ndarray, what: str) -> None:
    """WireError (bad_score) naming the first score outside [0, 1]."""
    bad = (scores < 0) | (scores > 1)
    if bad.any():
        raise WireError(
            topic,
            "score",
            f"{float(scores[np.argmax(bad)]):g} outside [0, 1] in {what} {int(np.argmax(bad))}",
            "bad_score",
        )
