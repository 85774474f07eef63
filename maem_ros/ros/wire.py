"""core <-> ROS messages: the only module that knows the wire layouts (doc/design.md §4).

PointCloud2 layouts (one point per row, little-endian, packed, height 1):

* detections (``/<cam>/detections``), one point per detection, all float32:
  ``bbox``(4: x1 y1 x2 y2 rectified px) ``score``(1) ``kpts2d``(2J rectified px, u v per joint,
  NaN = keypoint not seen, e.g. under the frontend's visibility threshold)
  ``kpts3d``(3J m, camera-relative) ``verts2d``(2V rectified px). header.frame_id = camera name,
  header.stamp = image capture stamp. J and V come from the counts.
  Compact variant (:data:`WIRE_VERTICES` ``q4``): ``verts2d_q4`` (uint16 x 2V) instead of
  ``verts2d``, value = round((px - origin) * 16) (1/16 px steps over 4095.875 px from the origin),
  65535 = missing (outside that range); ``verts2d_q4_origin`` (f32 x 2, optional, default 0 0)
  is the detection's origin in px: the encoder puts it at the floor of the detection's smallest
  vertex coordinates, so people whose rectified vertices are negative or beyond 4096 px (wide,
  strongly distorted cameras) lose nothing; optionally ``kpts2d_q4`` (uint16 x 2J, 65535 = not seen) instead
  of ``kpts2d``. A vertex subset is announced by ``verts2d_subset`` (uint32 x 3: full mesh
  vertices, stride, count; core.association.gates.epipolar.vertex_subset gives the ids) in every point.
* clusters (``/maem/clusters``), one point per (cluster, member view): ``cluster``(uint32, index in
  the frame) ``camera``(uint16, index in the rig's camera order) ``detection``(uint16, index in
  that camera's detections message) ``score``(f32) ``cost``(f32, mean PA-MPJPE m to the rest of
  the cluster, NaN if alone) ``kpts2d``(f32 x 2J rectified px). header.stamp = frame-set stamp.
  With temporal association also ``track``(uint32 track id, 4294967295 = tentative) and
  ``track_flags``(uint8, core.tracking.temporal FLAG_* bits: 1 tracked, 2 fewer than k_min views).
* poses (``/maem/poses``), one point per person: ``id``(uint32 track id, 4294967295 = not yet
  confirmed) ``joints``(f32 x 3J world m, NaN = missing) ``views``(uint16) ``score``(f32, see
  core/triangulation/uncertainty.py), optionally ``joint_std``(f32 x J, per-joint standard
  deviation in m, NaN where the joint is missing; decoders that read fields by name ignore it).

Decoders build one numpy structured dtype from msg.fields and view msg.data with np.frombuffer
(no copy of the payload). Any problem raises :class:`WireError` (a ValueError) naming topic,
field and problem, with a short ``reason`` code for /diagnostics.
"""
from __future__ import annotations

import array
import importlib
import struct
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.colors import id_rgb
from maem_ros.core.detections import FrameDetections
from maem_ros.core.association.gates.epipolar import screen_copies
from maem_ros.core.geometry.frames import FrameTransform
from maem_ros.core.errors import InputError

#: poses ``id`` of a person whose track is not confirmed yet
UNTRACKED_ID = 0xFFFFFFFF
#: marker namespaces; marker id = track id in each
NS_JOINTS, NS_BONES, NS_LABELS = "skeleton/joints", "skeleton/bones", "skeleton/ids"
#: namespace of the DELETEALL marker that starts every skeleton MarkerArray
NS_DELETE_ALL = "skeleton"

_NP_OF_PF = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2",
             PointField.UINT16: "u2", PointField.INT32: "i4", PointField.UINT32: "u4",
             PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}
_PF_NAME = {PointField.INT8: "INT8", PointField.UINT8: "UINT8", PointField.INT16: "INT16",
            PointField.UINT16: "UINT16", PointField.INT32: "INT32", PointField.UINT32: "UINT32",
            PointField.FLOAT32: "FLOAT32", PointField.FLOAT64: "FLOAT64"}

F32, U32, U16 = PointField.FLOAT32, PointField.UINT32, PointField.UINT16
DETECTION_TYPES = {"bbox": F32, "score": F32, "kpts2d": F32, "kpts3d": F32, "verts2d": F32}
#: the compact fields, each replacing the float32 field of the same name without ``_q4``
Q4_FIELDS = {"kpts2d_q4": "kpts2d", "verts2d_q4": "verts2d"}
#: optional field announcing a vertex subset: (full mesh vertices, stride, count)
SUBSET_FIELD = "verts2d_subset"
#: optional per-detection origin (px) of the verts2d_q4 codes
ORIGIN_FIELD = "verts2d_q4_origin"
#: frontend ``wire_vertices`` choices
WIRE_VERTICES = ("f32", "q4")
#: q4: 1/16 px steps; the largest code is the missing marker
Q4_SCALE, Q4_MISSING = 16.0, 65535
CLUSTER_TYPES = {"cluster": U32, "camera": U16, "detection": U16, "score": F32, "cost": F32,
                 "kpts2d": F32}
#: optional cluster fields, written with temporal association: ``track``(uint32 track id,
#: UNTRACKED_ID = tentative) ``track_flags``(uint8, core.tracking.temporal FLAG_* bits)
CLUSTER_TRACK_TYPES = {"track": U32, "track_flags": PointField.UINT8}
POSE_TYPES = {"id": U32, "joints": F32, "views": U16, "score": F32}
POSE_OPTIONAL = {"joint_std": F32}


class WireError(InputError):
    """A message that cannot be decoded: ``topic: field: problem`` plus a diagnostics reason."""

    def __init__(self, topic: str, field: str, problem: str, reason: str):
        super().__init__(f"{topic}: {field}: {problem}", reason)
        self.topic, self.field, self.problem = topic, field, problem


# ---------------------------------------------------------------------------------------------
# stamps
# ---------------------------------------------------------------------------------------------
def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def checked_stamp_ns(stamp: Time, topic: str) -> int:
    """stamp_to_ns for a received header: WireError (reason bad_stamp) for a negative sec or a
    nanosec outside 0..999,999,999, which would otherwise decode to a wrong instant."""
    if stamp.sec < 0 or not 0 <= stamp.nanosec < 1_000_000_000:
        raise WireError(topic, "header.stamp", f"invalid stamp sec={stamp.sec} "
                        f"nanosec={stamp.nanosec}", "bad_stamp")
    return stamp_to_ns(stamp)


#: builtin_interfaces/Time.sec is int32: stamps from 0 up to 2^31 s (2038-01-19) fit
MAX_STAMP_NS = 2**31 * 1_000_000_000 - 1


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (0 .. MAX_STAMP_NS) -> builtin_interfaces/Time; ValueError outside."""
    if not 0 <= int(ns) <= MAX_STAMP_NS:
        raise ValueError(f"stamp: {int(ns)} ns is outside builtin_interfaces/Time (0 .. 2^31 s)")
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def cdr_header_stamp_ns(data: bytes) -> int:
    """Header stamp of a serialized message whose first field is std_msgs/Header (CDR: 4-byte
    encapsulation header, then builtin_interfaces/Time sec int32, nanosec uint32), without
    deserialising the rest."""
    if len(data) < 12:
        raise ValueError(f"serialized message: {len(data)} bytes, too short for a header")
    endian = "<" if data[1] & 1 else ">"
    sec, nsec = struct.unpack_from(endian + "iI", data, 4)
    return sec * 1_000_000_000 + nsec


def cdr_to_cloud(data: bytes, topic: str):
    """A serialized sensor_msgs/PointCloud2 (CDR, what a raw subscription takes) -> a message
    the decoders here read, its ``data`` a numpy view into ``data`` (no copy).

    Why not rclpy's own deserialisation: it converts the uint8[] payload into an array.array
    element by element, which for six 1.8 MB full-mesh detections messages a frame cost more
    than the association itself, where the rosbags decoder on a memoryview slices the payload
    without touching it. WireError (reason ``bad_cdr``) for bytes that are no PointCloud2."""
    from maem_ros import bagio
    try:
        # a memoryview: rosbags slices it for the uint8[] payload (a bytes slice would copy)
        return bagio.deserialize(memoryview(data), bagio.POINT_CLOUD2)
    except Exception as e:  # noqa: BLE001 - any decoder failure is the same bad input
        raise WireError(topic, "data", f"not a serialized PointCloud2 ({len(data)} bytes: "
                        f"{type(e).__name__}: {e})", "bad_cdr") from None


def warm_cdr_decoder() -> None:
    """Build the PointCloud2 decoder cdr_to_cloud uses now (rosbags generates and compiles it
    on first use), so the first frame after start-up does not pay for it."""
    from rclpy.serialization import serialize_message
    cdr_to_cloud(bytes(serialize_message(PointCloud2())), "warm-up")


def make_header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


# ---------------------------------------------------------------------------------------------
# generic PointCloud2 <-> structured array
# ---------------------------------------------------------------------------------------------
def _packed_dtype(fields: Sequence[tuple[str, int, int]]) -> np.dtype:
    """Packed little-endian structured dtype for [(name, PointField datatype, count)]."""
    names, formats, offsets, off = [], [], [], 0
    for name, dt, count in fields:
        base = np.dtype("<" + _NP_OF_PF[dt])
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(off)
        off += base.itemsize * count
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})


def _new_cloud(stamp_ns: int, frame_id: str, fields: Sequence[tuple[str, int, int]],
               n: int) -> tuple[PointCloud2, np.ndarray]:
    """An n-point PointCloud2 without data and a writable structured (n,) array; fill the array,
    then :func:`_set_data` (the generated setter copies array.array data when field checks are
    off, so the data is attached after filling)."""
    dtype = _packed_dtype(fields)
    msg = PointCloud2(header=make_header(stamp_ns, frame_id), height=1, width=n,
                      is_bigendian=False, point_step=dtype.itemsize, row_step=n * dtype.itemsize,
                      is_dense=True)
    msg.fields = [PointField(name=name, offset=dtype.fields[name][1], datatype=dt, count=count)
                  for name, dt, count in fields]
    buf = array.array("B", bytes(n * dtype.itemsize))
    return msg, np.frombuffer(buf, dtype=dtype, count=n)


def _set_data(msg: PointCloud2, rec: np.ndarray) -> PointCloud2:
    """Attach the filled structured array from :func:`_new_cloud` as msg.data (one memcpy)."""
    base = rec.base.obj if isinstance(rec.base, memoryview) else rec.base
    msg.data = base if isinstance(base, array.array) else array.array("B", rec.tobytes())
    return msg


def _view_cloud(msg: PointCloud2, topic: str, expected: Mapping[str, int],
                optional: Mapping[str, int] | None = None) -> np.ndarray:
    """Validate layout and return a structured (N,) view of msg.data (zero-copy).

    ``expected`` maps every required field name to its PointField datatype, ``optional`` the
    fields that may be absent; any other field is an error. Each field's count is returned as
    the subarray length (count 1 -> shape (N,1)).
    """
    present = {k: v for k, v in (optional or {}).items() if any(f.name == k for f in msg.fields)}
    expected = {**expected, **present}
    seen: dict[str, PointField] = {}
    for f in msg.fields:
        label = f.name or "''"
        if f.name in seen:
            raise WireError(topic, label, "field listed twice", "duplicate_field")
        if f.name not in expected:
            raise WireError(topic, label, f"unknown field (expected {sorted(expected)})",
                            "unknown_field")
        seen[f.name] = f
    missing = [k for k in expected if k not in seen]
    if missing:
        raise WireError(topic, missing[0], f"missing field (got {sorted(seen)})", "missing_field")
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets, spans = [], [], [], []
    step = int(msg.point_step)
    for name, dt in expected.items():
        f = seen[name]
        if f.datatype != dt:
            raise WireError(topic, name, f"datatype {_PF_NAME.get(f.datatype, f.datatype)}, "
                            f"expected {_PF_NAME[dt]}", "bad_datatype")
        base = np.dtype(endian + _NP_OF_PF[dt])
        size = base.itemsize * int(f.count)
        if f.offset + size > step:
            raise WireError(topic, name, f"offset {f.offset} + {size} bytes exceeds point_step "
                            f"{step}", "bad_layout")
        names.append(name)
        formats.append((base, (int(f.count),)))
        offsets.append(int(f.offset))
        spans.append((int(f.offset), int(f.offset) + size, name))
    spans.sort()
    for (a0, a1, an), (b0, _, bn) in zip(spans, spans[1:]):
        if b0 < a1:
            raise WireError(topic, bn, f"overlaps field {an!r}", "bad_layout")
    n = int(msg.width) * int(msg.height)
    if n and step <= 0:
        raise WireError(topic, "point_step", f"{step} with {n} points", "bad_size")
    if int(msg.height) > 1 and int(msg.row_step) != int(msg.width) * step:
        raise WireError(topic, "row_step", f"{msg.row_step} != width {msg.width} x point_step "
                        f"{step}", "bad_size")
    if int(msg.height) <= 1 and n and int(msg.row_step) != n * step:
        raise WireError(topic, "row_step", f"{msg.row_step} != width {msg.width} x point_step "
                        f"{step}", "bad_size")
    if len(msg.data) != n * step:
        raise WireError(topic, "data", f"{len(msg.data)} bytes, expected {n} points x "
                        f"{step} bytes", "bad_size")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": max(step, 1)})
    if n == 0:
        return np.zeros(0, dtype=dtype)
    return np.frombuffer(msg.data, dtype=dtype, count=n)


def _field(rec: np.ndarray, name: str) -> np.ndarray:
    """(N, count) view of one field in native byte order (copy only for big-endian data)."""
    arr = rec[name]
    return arr if arr.dtype.isnative else arr.astype(arr.dtype.newbyteorder("="))


def _count(msg: PointCloud2, name: str) -> int:
    return next(int(f.count) for f in msg.fields if f.name == name)


def _check_finite(topic: str, name: str, arr: np.ndarray, what: str = "detection",
                  allow_nan: bool = False) -> None:
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        row = int(np.argwhere(bad.reshape(len(arr), -1).any(axis=1))[0][0])
        raise WireError(topic, name, f"{'inf' if allow_nan else 'NaN or inf'} in {what} {row}",
                        "nonfinite")


def _check_score(topic: str, scores: np.ndarray, what: str) -> None:
    bad = (scores < 0) | (scores > 1)
    if bad.any():
        raise WireError(topic, "score", f"{float(scores[np.argmax(bad)]):g} outside [0, 1] in "
                        f"{what} {int(np.argmax(bad))}", "bad_score")


# ---------------------------------------------------------------------------------------------
# detections
# ---------------------------------------------------------------------------------------------
def encode_q4(px: np.ndarray) -> np.ndarray:
    """Rectified px -> uint16 q4 codes (round(px * 16)); NaN and values outside
    0 .. 4095.9375 px become Q4_MISSING."""
    px = np.asarray(px, dtype=np.float64)
    code = np.rint(px * Q4_SCALE)
    ok = (code >= 0) & (code < Q4_MISSING)  # False for NaN
    return np.where(ok, code, Q4_MISSING).astype(np.uint16)


def decode_q4(code: np.ndarray, dtype=np.float32, origin: np.ndarray | None = None) -> np.ndarray:
    """uint16 q4 codes (N, 2K) -> px (``dtype``), NaN where the code is Q4_MISSING (one copy);
    ``origin`` (N, 2) px is added to every (u, v).

    Written for speed on a full mesh (442k codes, an order of magnitude faster than the
    obvious expression): cast, then scale in place (a multiply that casts on the way is much
    slower), the origin added to each
    (u, v) pair as one complex number (contiguous rows; a broadcast over pairs has an inner
    loop of length 2; complex addition is the same two float additions), NaN written only
    when a code is missing."""
    out = np.asarray(code).astype(dtype)
    out *= dtype(1.0 / Q4_SCALE)
    if origin is not None and len(out) and out.shape[1]:
        cplx = np.complex64 if out.dtype == np.float32 else np.complex128
        shift = (origin[:, 0] + 1j * origin[:, 1]).astype(cplx)
        out.view(cplx)[:] += shift[:, None]
    if out.size and code.max() == Q4_MISSING:
        out[code == Q4_MISSING] = np.nan
    return out


def q4_origin(verts2d: np.ndarray) -> np.ndarray:
    """(N, 2) px origin of each detection's q4 codes: the floor of its smallest finite vertex
    coordinates (0 where it has none), an integer so origin + code / 16 is exact in float32."""
    with np.errstate(invalid="ignore"):
        lo = np.nanmin(np.where(np.isfinite(verts2d), verts2d, np.nan), axis=1) \
            if verts2d.shape[1] else np.zeros((len(verts2d), 2))
    return np.floor(np.nan_to_num(lo, nan=0.0)).astype(np.float32)


def detections_to_msg(dets: FrameDetections, vertices: str = "f32",
                      keypoints: str = "f32") -> PointCloud2:
    """FrameDetections -> PointCloud2 (frame_id = camera, stamp = image stamp).

    ``vertices`` / ``keypoints``: ``f32`` (verts2d / kpts2d float32) or ``q4`` (verts2d_q4 /
    kpts2d_q4 uint16, 1/16 px). A vertex outside 0 .. 4095.875 px is sent as missing (65535);
    a seen keypoint is never dropped: a message with a keypoint q4 cannot carry sends kpts2d as
    f32 (a keypoint not seen, NaN, is 65535 in q4).
    A vertex subset held by ``dets`` (mesh_subset) is announced in verts2d_subset.
    """
    for name, value in (("vertices", vertices), ("keypoints", keypoints)):
        if value not in WIRE_VERTICES:
            raise ValueError(f"{name}: expected one of {list(WIRE_VERTICES)}, got {value!r}")
    n, j, v = dets.n, dets.num_joints, dets.num_vertices
    kp = dets.kpts2d.reshape(n, 2 * j)
    k_code = encode_q4(kp) if keypoints == "q4" else None
    if k_code is not None and ((k_code == Q4_MISSING) & ~np.isnan(kp)).any():
        k_code = None  # a keypoint outside 0 .. 4095.875 px: this message carries f32 keypoints
    k_field = ("kpts2d_q4", U16) if k_code is not None else ("kpts2d", F32)
    v_field = ("verts2d_q4", U16) if vertices == "q4" else ("verts2d", F32)
    fields = [("bbox", F32, 4), ("score", F32, 1), (*k_field, 2 * j), ("kpts3d", F32, 3 * j),
              (*v_field, 2 * v)]
    if vertices == "q4":
        fields.append((ORIGIN_FIELD, F32, 2))
    if dets.mesh_subset is not None:
        fields.append((SUBSET_FIELD, U32, 3))
    msg, rec = _new_cloud(dets.stamp_ns, dets.camera, fields, n)
    if n:
        rec["bbox"] = dets.bboxes
        rec["score"] = dets.scores
        if k_code is not None:
            rec["kpts2d_q4"] = k_code
        else:
            rec["kpts2d"] = kp
        rec["kpts3d"] = dets.kpts3d.reshape(n, 3 * j)
        vp = dets.verts2d.reshape(n, 2 * v)
        if vertices == "q4":
            origin = q4_origin(dets.verts2d)
            rec[ORIGIN_FIELD] = origin
            rec["verts2d_q4"] = encode_q4((dets.verts2d - origin[:, None, :]).reshape(n, 2 * v))
        else:
            rec["verts2d"] = vp
        if dets.mesh_subset is not None:
            rec[SUBSET_FIELD] = np.asarray(dets.mesh_subset, dtype=np.uint32)
    return _set_data(msg, rec)


def _detection_layout(msg: PointCloud2, topic: str) -> dict[str, int]:
    """Field name -> PointField datatype of this detections message (f32 or q4 variants)."""
    names = {f.name for f in msg.fields}
    expected = dict(DETECTION_TYPES)
    for q4, plain in Q4_FIELDS.items():
        if q4 in names:
            if plain in names:
                raise WireError(topic, q4, f"both {plain!r} and {q4!r} present", "duplicate_field")
            del expected[plain]
            expected[q4] = U16
    if SUBSET_FIELD in names:
        expected[SUBSET_FIELD] = U32
    if ORIGIN_FIELD in names:
        if "verts2d_q4" not in names:
            raise WireError(topic, ORIGIN_FIELD, "without verts2d_q4", "unknown_field")
        expected[ORIGIN_FIELD] = F32
    return expected


def _mesh_subset(topic: str, sub: np.ndarray, v: int) -> tuple[int, int, int]:
    """The announced (mesh vertices, stride, count), identical in every point and giving V ids."""
    if len(sub) and np.any(sub != sub[0]):
        row = int(np.argmax(np.any(sub != sub[0], axis=1)))
        raise WireError(topic, SUBSET_FIELD, f"detection {row} announces {sub[row].tolist()}, "
                        f"detection 0 {sub[0].tolist()}", "bad_subset")
    mesh, stride, count = (int(x) for x in sub[0])
    from maem_ros.core.association.gates.epipolar import vertex_subset
    if stride < 1 or mesh < v:
        raise WireError(topic, SUBSET_FIELD, f"(mesh {mesh}, stride {stride}, count {count}) "
                        f"for {v} vertices", "bad_subset")
    ids = vertex_subset(mesh, stride, count)
    got = mesh if ids is None else ids.size
    if got != v:
        raise WireError(topic, SUBSET_FIELD, f"(mesh {mesh}, stride {stride}, count {count}) "
                        f"selects {got} vertices, verts2d has {v}", "bad_subset")
    return mesh, stride, count


def msg_to_detections(msg: PointCloud2, topic: str,
                      known_cameras: Sequence[str] | None = None,
                      expected_camera: str | None = None,
                      screen_strides: Sequence[int] = ()) -> FrameDetections:
    """PointCloud2 -> FrameDetections, validated once (the result is marked validated, so the
    association does not check the arrays again); f32 verts2d is a view of msg.data, q4 codes
    are decoded once into one float32 array (NaN = missing).

    ``known_cameras``: frame_id must be one of them; ``expected_camera``: frame_id must equal it
    (the camera whose topic this came from). ``screen_strides``: the mesh gate's screening
    subsets of verts2d to copy in the pass that checks verts2d
    (core.association.pipeline.decode_screen_strides; FrameDetections.attach_screens).
    """
    cam = msg.header.frame_id
    if known_cameras is not None and cam not in known_cameras:
        raise WireError(topic, "header.frame_id", f"unknown camera {cam!r} (rig has "
                        f"{list(known_cameras)})", "unknown_camera")
    if expected_camera is not None and cam != expected_camera:
        raise WireError(topic, "header.frame_id", f"camera {cam!r} on the topic of camera "
                        f"{expected_camera!r}", "camera_mismatch")
    layout = _detection_layout(msg, topic)
    rec = _view_cloud(msg, topic, layout)
    counts = {name: _count(msg, name) for name in layout}
    kname = "kpts2d_q4" if "kpts2d_q4" in layout else "kpts2d"
    vname = "verts2d_q4" if "verts2d_q4" in layout else "verts2d"
    if counts["bbox"] != 4:
        raise WireError(topic, "bbox", f"count {counts['bbox']}, expected 4", "bad_count")
    if counts["score"] != 1:
        raise WireError(topic, "score", f"count {counts['score']}, expected 1", "bad_count")
    if counts[kname] % 2 or counts[kname] == 0:
        raise WireError(topic, kname, f"count {counts[kname]}, expected 2J (J >= 1)",
                        "bad_count")
    j = counts[kname] // 2
    if counts["kpts3d"] != 3 * j:
        raise WireError(topic, "kpts3d", f"count {counts['kpts3d']}, expected 3J = {3 * j} "
                        f"(J={j} from {kname})", "bad_count")
    if counts[vname] % 2:
        raise WireError(topic, vname, f"count {counts[vname]}, expected 2V", "bad_count")
    if ORIGIN_FIELD in layout and counts[ORIGIN_FIELD] != 2:
        raise WireError(topic, ORIGIN_FIELD, f"count {counts[ORIGIN_FIELD]}, expected 2 (u v px)",
                        "bad_count")
    if SUBSET_FIELD in layout and counts[SUBSET_FIELD] != 3:
        raise WireError(topic, SUBSET_FIELD, f"count {counts[SUBSET_FIELD]}, expected 3 (mesh "
                        f"vertices, stride, count)", "bad_count")
    n, v = len(rec), counts[vname] // 2
    fields = {name: _field(rec, name) for name in layout}
    for name in ("bbox", "score", "kpts3d"):
        _check_finite(topic, name, fields[name])
    if kname == "kpts2d_q4":  # 65535 = keypoint missing (NaN), as for vertices
        kpts2d = decode_q4(fields[kname], np.float64)
    else:
        _check_finite(topic, "kpts2d", fields["kpts2d"], allow_nan=True)  # NaN = not seen
        kpts2d = fields["kpts2d"]
    copies: dict[int, np.ndarray] = {}
    ranges: dict[int, np.ndarray] = {}
    if vname == "verts2d_q4":
        origin = fields.get(ORIGIN_FIELD)
        if origin is not None:
            _check_finite(topic, ORIGIN_FIELD, origin)
        verts2d = decode_q4(fields[vname], origin=origin)
        if screen_strides:
            copies, ranges, _ = screen_copies(verts2d.reshape(n, v, 2), screen_strides)
    elif screen_strides:  # the check and the copies in one pass
        verts2d = fields["verts2d"]
        copies, ranges, row = screen_copies(verts2d.reshape(n, v, 2), screen_strides)
        if row >= 0:
            raise WireError(topic, "verts2d", f"inf in detection {row}", "nonfinite")
    else:
        verts2d = fields["verts2d"]
        _check_finite(topic, "verts2d", verts2d, allow_nan=True)  # NaN = missing vertex
    bbox = fields["bbox"]
    inverted = (bbox[:, 2] < bbox[:, 0]) | (bbox[:, 3] < bbox[:, 1])
    if inverted.any():
        raise WireError(topic, "bbox", f"inverted box (x2<x1 or y2<y1) in detection "
                        f"{int(np.argmax(inverted))}", "inverted_bbox")
    _check_score(topic, fields["score"][:, 0], "detection")
    subset = _mesh_subset(topic, fields[SUBSET_FIELD], v) if SUBSET_FIELD in layout and n \
        else None
    return FrameDetections(
        camera=cam, stamp_ns=checked_stamp_ns(msg.header.stamp, topic), bboxes=bbox,
        scores=fields["score"][:, 0], kpts2d=kpts2d.reshape(n, j, 2),
        kpts3d=fields["kpts3d"].reshape(n, j, 3), verts2d=verts2d.reshape(n, v, 2),
        mesh_subset=subset).mark_validated().attach_screens(copies, ranges)


# ---------------------------------------------------------------------------------------------
# clusters
# ---------------------------------------------------------------------------------------------
@dataclass
class ClusterFrame:
    """Decoded /maem/clusters: M member rows (cluster, camera index, detection, score, cost, kpts2d).

    kpts2d (M,J,2) rectified px; cost (M,) metres (NaN = member alone).
    """

    stamp_ns: int
    frame_id: str
    cluster: np.ndarray
    camera: np.ndarray
    detection: np.ndarray
    score: np.ndarray
    cost: np.ndarray
    kpts2d: np.ndarray
    track: np.ndarray | None = None  # (M,) int64 track id per row, -1 = tentative; None = untracked
    track_flags: np.ndarray | None = None  # (M,) uint8 core.tracking.temporal FLAG_* bits

    @property
    def num_joints(self) -> int:
        return int(self.kpts2d.shape[1])

    def dense(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Dense padded member arrays for core.triangulation.ransac.triangulate_members: cam (C,M),
        kpts2d (C,M,J,2), score (C,M), present (C,M); clusters in order of first row."""
        from maem_ros.core.triangulation.ransac import pad_members  # local: wire stays importable alone
        return pad_members(self.cluster, self.camera.astype(np.int64),
                           self.kpts2d.astype(np.float64), self.score.astype(np.float64))

    def cluster_tracks(self) -> np.ndarray | None:
        """(C,) track id per cluster in to_core order (-1 = tentative), None without tracks."""
        if self.track is None:
            return None
        _, first = np.unique(self.cluster, return_index=True)
        return self.track[np.sort(first)]


def clusters_to_msg(stamp_ns: int, frame_id: str, rig: Rig,
                    frames: Mapping[str, FrameDetections], clusters: Sequence,
                    track_ids: Sequence[int] | None = None,
                    track_flags: Sequence[int] | None = None) -> PointCloud2:
    """core Clusters (members = (camera index, detection index)) -> PointCloud2.

    ``frames`` are the FrameDetections the clusters index into, keyed by camera name; J is
    taken from them (0 points and J of any frame when there are no clusters). With
    ``track_ids`` (one per cluster, < 0 = tentative) the optional ``track`` and ``track_flags``
    fields are written too.
    """
    j = next((f.num_joints for f in frames.values()), 0)
    members, costs = [], []  # one row per (cluster, member); a member without a cost: no row
    for cl in clusters:
        m, c = np.asarray(cl.members, np.int64).reshape(-1, 2), np.asarray(cl.costs).reshape(-1)
        n = min(len(m), len(c))
        members.append(m[:n])
        costs.append(c[:n])
    per_row = np.repeat(np.arange(len(clusters)), [len(m) for m in members])
    fields = [("cluster", U32, 1), ("camera", U16, 1), ("detection", U16, 1), ("score", F32, 1),
              ("cost", F32, 1), ("kpts2d", F32, 2 * j)]
    if track_ids is not None:
        fields += [(name, dt, 1) for name, dt in CLUSTER_TRACK_TYPES.items()]
    msg, rec = _new_cloud(stamp_ns, frame_id, fields, len(per_row))
    if not len(per_row):
        return _set_data(msg, rec)
    if track_ids is not None:
        ids = np.asarray(track_ids, np.int64)[per_row]
        rec["track"] = np.where(ids < 0, UNTRACKED_ID, ids).astype(np.uint32)
        flags = np.zeros(len(clusters), np.uint8) if track_flags is None else track_flags
        rec["track_flags"] = np.asarray(flags, np.uint8)[per_row]
    cam_det = np.concatenate(members)
    rec["cluster"] = per_row
    rec["camera"] = cam_det[:, 0]
    rec["detection"] = cam_det[:, 1]
    rec["cost"] = np.concatenate(costs)
    names = rig.names
    for c in np.unique(cam_det[:, 0]):  # gathered per camera: rows index into its detections
        rows = cam_det[:, 0] == c
        f, d = frames[names[c]], cam_det[rows, 1]
        rec["score"][rows] = f.scores[d]
        rec["kpts2d"][rows] = f.kpts2d[d].reshape(len(d), -1)
    return _set_data(msg, rec)


def msg_to_clusters(msg: PointCloud2, topic: str, num_cameras: int) -> ClusterFrame:
    """PointCloud2 -> ClusterFrame, validated (camera index < num_cameras, unique members)."""
    rec = _view_cloud(msg, topic, CLUSTER_TYPES, CLUSTER_TRACK_TYPES)
    tracked = "track" in rec.dtype.names
    if tracked != ("track_flags" in rec.dtype.names):
        raise WireError(topic, "track" if not tracked else "track_flags",
                        "missing field (track and track_flags come together)", "missing_field")
    for name in ("cluster", "camera", "detection", "score", "cost") + (
            tuple(CLUSTER_TRACK_TYPES) if tracked else ()):
        if _count(msg, name) != 1:
            raise WireError(topic, name, f"count {_count(msg, name)}, expected 1", "bad_count")
    c2 = _count(msg, "kpts2d")
    if c2 % 2 or c2 == 0:
        raise WireError(topic, "kpts2d", f"count {c2}, expected 2J (J >= 1)", "bad_count")
    n = len(rec)
    f = {name: _field(rec, name) for name in CLUSTER_TYPES}
    camera = f["camera"][:, 0].astype(np.int64)
    if n and camera.max() >= num_cameras:
        raise WireError(topic, "camera", f"index {int(camera.max())} but the rig has "
                        f"{num_cameras} cameras", "unknown_camera")
    pairs = camera * 65536 + f["detection"][:, 0]
    if len(np.unique(pairs)) != n:
        raise WireError(topic, "detection", "a (camera, detection) pair appears twice",
                        "duplicate_member")
    _check_finite(topic, "kpts2d", f["kpts2d"], "member", allow_nan=True)  # NaN = not seen
    _check_finite(topic, "score", f["score"], "member")
    _check_finite(topic, "cost", f["cost"], "member", allow_nan=True)
    _check_score(topic, f["score"][:, 0], "member")
    track = flags = None
    if tracked:
        raw = _field(rec, "track")[:, 0].astype(np.int64)
        track = np.where(raw == UNTRACKED_ID, -1, raw)
        flags = _field(rec, "track_flags")[:, 0].astype(np.uint8)
        cluster = f["cluster"][:, 0].astype(np.int64)
        _, first, inverse = np.unique(cluster, return_index=True, return_inverse=True)
        if np.any(track != track[first][inverse]):
            raise WireError(topic, "track", "members of one cluster carry different track ids",
                            "bad_track")
    return ClusterFrame(track=track, track_flags=flags,
                        stamp_ns=checked_stamp_ns(msg.header.stamp, topic), frame_id=msg.header.frame_id,
                        cluster=f["cluster"][:, 0].astype(np.int64), camera=camera,
                        detection=f["detection"][:, 0].astype(np.int64),
                        score=f["score"][:, 0].astype(np.float64),
                        cost=f["cost"][:, 0].astype(np.float64),
                        kpts2d=f["kpts2d"].reshape(n, c2 // 2, 2).astype(np.float64))


# ---------------------------------------------------------------------------------------------
# poses
# ---------------------------------------------------------------------------------------------
@dataclass
class PoseFrame:
    """Decoded /maem/poses: ids (P,) int64, joints (P,J,3) world m (NaN = missing), views, scores,
    joint_std (P,J) m or None when the message has no ``joint_std`` field."""

    stamp_ns: int
    frame_id: str
    ids: np.ndarray
    joints: np.ndarray
    views: np.ndarray
    scores: np.ndarray
    joint_std: np.ndarray | None = None


def poses_to_msg(stamp_ns: int, frame_id: str, ids: np.ndarray, joints: np.ndarray,
                 views: np.ndarray, scores: np.ndarray,
                 joint_std: np.ndarray | None = None) -> PointCloud2:
    """Persons -> PointCloud2; ids < 0 (tentative tracks) are sent as UNTRACKED_ID; the
    ``joint_std`` field (P,J) m is written when given."""
    joints = np.asarray(joints, dtype=np.float64)
    p = int(joints.shape[0])
    j = int(joints.shape[1]) if joints.ndim == 3 else 0
    fields = [("id", U32, 1), ("joints", F32, 3 * j), ("views", U16, 1), ("score", F32, 1)]
    if joint_std is not None:
        fields.append(("joint_std", F32, j))
    msg, rec = _new_cloud(stamp_ns, frame_id, fields, p)
    if p:
        ids = np.asarray(ids, dtype=np.int64)
        rec["id"] = np.where(ids < 0, UNTRACKED_ID, ids).astype(np.uint32)
        rec["joints"] = joints.reshape(p, 3 * j)
        rec["views"] = np.clip(np.asarray(views), 0, 65535).astype(np.uint16)
        rec["score"] = np.asarray(scores, dtype=np.float32)
        if joint_std is not None:
            rec["joint_std"] = np.asarray(joint_std, dtype=np.float32).reshape(p, j)
    return _set_data(msg, rec)


def msg_to_poses(msg: PointCloud2, topic: str) -> PoseFrame:
    """PointCloud2 -> PoseFrame (NaN joints allowed, inf not)."""
    rec = _view_cloud(msg, topic, POSE_TYPES, POSE_OPTIONAL)
    for name in ("id", "views", "score"):
        if _count(msg, name) != 1:
            raise WireError(topic, name, f"count {_count(msg, name)}, expected 1", "bad_count")
    c3 = _count(msg, "joints")
    if c3 % 3:
        raise WireError(topic, "joints", f"count {c3}, expected 3J", "bad_count")
    f = {name: _field(rec, name) for name in POSE_TYPES}
    _check_finite(topic, "joints", f["joints"], "person", allow_nan=True)
    _check_finite(topic, "score", f["score"], "person")
    n = len(rec)
    return PoseFrame(stamp_ns=checked_stamp_ns(msg.header.stamp, topic), frame_id=msg.header.frame_id,
                     ids=f["id"][:, 0].astype(np.int64),
                     joints=f["joints"].reshape(n, c3 // 3, 3).astype(np.float64),
                     views=f["views"][:, 0].astype(np.int64),
                     scores=f["score"][:, 0].astype(np.float64),
                     joint_std=_pose_joint_std(msg, rec, topic, c3 // 3))


def _pose_joint_std(msg: PointCloud2, rec: np.ndarray, topic: str, j: int) -> np.ndarray | None:
    """The optional ``joint_std`` field (P,J) m of a poses message, None when absent."""
    if "joint_std" not in (rec.dtype.names or ()):
        return None
    if _count(msg, "joint_std") != j:
        raise WireError(topic, "joint_std", f"count {_count(msg, 'joint_std')}, expected J={j}",
                        "bad_count")
    std = _field(rec, "joint_std")
    _check_finite(topic, "joint_std", std, "person", allow_nan=True)
    if (std < 0).any():
        raise WireError(topic, "joint_std", "negative standard deviation", "bad_value")
    return std.reshape(len(rec), j).astype(np.float64)


# ---------------------------------------------------------------------------------------------
# skeleton markers
# ---------------------------------------------------------------------------------------------
def id_color(track_id: int, alpha: float = 1.0) -> ColorRGBA:
    """The id's colour (core.colors.id_rgb) as std_msgs/ColorRGBA."""
    r, g, b = id_rgb(track_id)
    return ColorRGBA(r=r, g=g, b=b, a=float(alpha))


def skeleton_markers(stamp_ns: int, frame_id: str, ids: Sequence[int], joints: np.ndarray,
                     bones: Sequence[tuple[int, int]], lifetime_s: float = 0.5,
                     joint_diameter: float = 0.06, bone_width: float = 0.03) -> MarkerArray:
    """Per person: SPHERE_LIST joints (ns skeleton/joints), LINE_LIST bones (ns skeleton/bones,
    bones with a NaN end skipped), TEXT_VIEW_FACING id 0.3 m above the highest joint
    (ns skeleton/ids). Marker id = track id in each ns; persons with id < 0 or no finite joint
    are skipped. The array starts with a DELETEALL marker (ns NS_DELETE_ALL), so each frame
    replaces the previous one whatever the replay rate; markers also expire after
    ``lifetime_s`` (> 0) so the view empties when the stream stops.
    """
    header = make_header(stamp_ns, frame_id)
    sec, nsec = divmod(int(round(lifetime_s * 1e9)), 1_000_000_000)
    life = Duration(sec=sec, nanosec=nsec)
    out = MarkerArray(markers=[Marker(header=header, ns=NS_DELETE_ALL, id=0,
                                      action=Marker.DELETEALL)])
    if len(ids) == 0:
        return out
    pj = np.asarray(joints, dtype=np.float64)  # (P, J, 3)
    pid = np.asarray(ids, dtype=np.int64)
    finite = np.isfinite(pj).all(axis=2)  # (P, J)
    ends = np.asarray(bones, dtype=np.intp).reshape(-1, 2)
    bone_ok = finite[:, ends[:, 0]] & finite[:, ends[:, 1]]  # (P, B)
    height = np.where(finite, pj[..., 2], -np.inf)
    top = pj[np.arange(len(pj)), np.argmax(height, axis=1)] if pj.shape[1] else pj[:, :0]
    shown = np.flatnonzero((pid >= 0) & finite.any(axis=1))
    # the message types need one Point object per point: one per shown finite joint, built
    # from one plain list and shared by the joint and bone lists (same values on the wire)
    seen = np.zeros_like(finite)
    seen[shown] = finite[shown]
    points = _points(pj[seen])
    slot = np.cumsum(seen).reshape(seen.shape) - 1  # (P, J) index into points where seen
    first = np.concatenate([[0], np.cumsum(seen.sum(1))])
    for p in shown.tolist():
        color, mid = id_color(int(pid[p])), int(pid[p])
        joint_m = Marker(header=header, ns=NS_JOINTS, id=mid, type=Marker.SPHERE_LIST,
                         action=Marker.ADD, lifetime=life, color=color,
                         points=points[first[p]:first[p + 1]])
        joint_m.pose.orientation.w = 1.0
        joint_m.scale.x = joint_m.scale.y = joint_m.scale.z = joint_diameter
        bone_m = Marker(header=header, ns=NS_BONES, id=mid, type=Marker.LINE_LIST,
                        action=Marker.ADD, lifetime=life, color=color,
                        points=[points[k] for k in slot[p][ends[bone_ok[p]]].ravel().tolist()])
        bone_m.pose.orientation.w = 1.0
        bone_m.scale.x = bone_width
        text_m = Marker(header=header, ns=NS_LABELS, id=mid, type=Marker.TEXT_VIEW_FACING,
                        action=Marker.ADD, lifetime=life, text=str(mid), color=color)
        x, y, z = top[p].tolist()
        text_m.pose.position = Point(x=x, y=y, z=z + 0.3)
        text_m.pose.orientation.w = 1.0
        text_m.scale.z = 0.25
        out.markers.extend([joint_m, bone_m, text_m])
    return out


def _points(xyz: np.ndarray) -> list[Point]:
    """(N, 3) -> geometry_msgs/Point list."""
    return [Point(x=x, y=y, z=z) for x, y, z in xyz.tolist()]


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
_IMAGE_CHANNELS = {"bgr8": 3, "rgb8": 3, "mono8": 1, "8UC1": 1, "8UC3": 3, "bgra8": 4,
                   "rgba8": 4}


def image_to_bgr(msg: Image, topic: str) -> np.ndarray:
    """sensor_msgs/Image (bgr8, rgb8, bgra8, rgba8, mono8) -> BGR uint8 (H,W,3)."""
    import cv2

    ch = _IMAGE_CHANNELS.get(msg.encoding)
    if ch is None:
        raise WireError(topic, "encoding", f"unsupported {msg.encoding!r}, expected one of "
                        f"{sorted(_IMAGE_CHANNELS)}", "bad_encoding")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise WireError(topic, "height/width", f"empty image {w}x{h}", "bad_size")
    if step < w * ch or len(msg.data) != h * step:
        raise WireError(topic, "data", f"{len(msg.data)} bytes for {w}x{h}x{ch} with step "
                        f"{step}", "bad_size")
    rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(h, step)
    img = rows[:, :w * ch].reshape(h, w, ch)
    if ch == 1:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if msg.encoding in ("rgb8", "rgba8"):
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGR)
    return img[:, :, :3] if ch == 4 else img


def compressed_to_bgr(msg: CompressedImage, topic: str) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg, png, ...) -> BGR uint8 (H,W,3) via cv2.imdecode."""
    import cv2

    if len(msg.data) == 0:
        raise WireError(topic, "data", "empty", "bad_size")
    img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise WireError(topic, "data", f"cannot decode {len(msg.data)} bytes (format "
                        f"{msg.format!r})", "bad_encoding")
    return img


def bgr_to_image(image: np.ndarray, stamp_ns: int, frame_id: str) -> Image:
    """BGR uint8 (H,W,3) -> sensor_msgs/Image bgr8."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = image.shape[:2]
    msg = Image(header=make_header(stamp_ns, frame_id), height=h, width=w, encoding="bgr8",
                is_bigendian=0, step=w * 3)
    msg.data = image.tobytes()
    return msg


#: CompressedImage.format of JPEG frames (image_transport 'compressed' convention)
JPEG_FORMAT = "bgr8; jpeg compressed bgr8"


def compressed_image_msg(data: bytes, fmt: str, stamp_ns: int, frame_id: str) -> CompressedImage:
    """sensor_msgs/CompressedImage carrying encoded bytes unchanged (``fmt`` e.g. "jpeg", "png")."""
    msg = CompressedImage(header=make_header(stamp_ns, frame_id), format=fmt)
    msg.data = bytes(data)
    return msg


def bgr_to_compressed(image: np.ndarray, stamp_ns: int, frame_id: str,
                      quality: int = 90) -> CompressedImage:
    """BGR uint8 (H,W,3) -> sensor_msgs/CompressedImage, JPEG at ``quality`` (1..100)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("image: JPEG encoding failed")
    return compressed_image_msg(buf.tobytes(), JPEG_FORMAT, stamp_ns, frame_id)


def camera_info_msg(camera: Camera, stamp_ns: int, frame_id: str) -> CameraInfo:
    """Camera -> sensor_msgs/CameraInfo of the RAW image: K, D and distortion model; R = I;
    P = [K_rect | 0] of the rectified image the frontends work in."""
    info = camera.to_camera_info()
    return CameraInfo(header=make_header(stamp_ns, frame_id), width=int(info["width"]),
                      height=int(info["height"]), distortion_model=str(info["distortion_model"]),
                      d=info["d"], k=info["k"], r=info["r"], p=info["p"])


# ---------------------------------------------------------------------------------------------
# TF (tf2_msgs/TFMessage): built for rclpy or, with ``types``, for rosbags
# ---------------------------------------------------------------------------------------------
#: topic of the rig's static transforms (ROS convention: global, transient local)
TF_STATIC_TOPIC = "/tf_static"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def _rclpy_type(msgtype: str):
    """The rclpy class of ``pkg/msg/Name`` (tf2_msgs is optional: ImportError when absent)."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def tf_message(transforms: Sequence[FrameTransform], stamp_ns: int,
               types: Mapping[str, type] | None = None):
    """tf2_msgs/TFMessage of core.geometry.frames transforms (one TransformStamped each, header.stamp =
    ``stamp_ns``). ``types``: msgtype -> class (e.g. the rosbags typestore's ``types``) to build
    the same layout for a bag writer; default rclpy (ImportError if tf2_msgs is not installed).
    """
    T = types.__getitem__ if types is not None else _rclpy_type
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    Time_, Header_ = T("builtin_interfaces/msg/Time"), T("std_msgs/msg/Header")
    Vector3, Quaternion = T("geometry_msgs/msg/Vector3"), T("geometry_msgs/msg/Quaternion")
    Transform, Stamped = T("geometry_msgs/msg/Transform"), T("geometry_msgs/msg/TransformStamped")
    out = []
    for tr in transforms:
        x, y, z = (float(v) for v in tr.translation)
        qx, qy, qz, qw = (float(v) for v in tr.quaternion)
        out.append(Stamped(header=Header_(stamp=Time_(sec=sec, nanosec=nsec), frame_id=tr.parent),
                           child_frame_id=tr.child,
                           transform=Transform(translation=Vector3(x=x, y=y, z=z),
                                               rotation=Quaternion(x=qx, y=qy, z=qz, w=qw))))
    return T(TF_MESSAGE)(transforms=out)


def msg_to_transforms(msg, topic: str) -> list[FrameTransform]:
    """TFMessage (rclpy or rosbags) -> core.geometry.frames transforms; WireError on a non-unit quaternion
    or a non-finite value."""
    out = []
    for i, ts in enumerate(msg.transforms):
        t, r = ts.transform.translation, ts.transform.rotation
        tr = np.array([t.x, t.y, t.z], dtype=np.float64)
        q = np.array([r.x, r.y, r.z, r.w], dtype=np.float64)
        if not (np.isfinite(tr).all() and np.isfinite(q).all()) or \
                abs(np.linalg.norm(q) - 1) > 1e-6:
            raise WireError(topic, f"transforms[{i}]", f"non-finite value or non-unit quaternion "
                            f"{q.tolist()}", "bad_transform")
        out.append(FrameTransform(ts.header.frame_id, ts.child_frame_id, tr, q))
    return out
