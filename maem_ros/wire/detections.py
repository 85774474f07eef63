"""Detections (``/<cam>/detections``): the layout with its compact q4 variant (see the
package docstring), encoded from and decoded to core FrameDetections. No rclpy."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections, vertex_subset
from maem_ros.wire.cdr import to_rosbags
from maem_ros.wire.cloud import (
    F32,
    U16,
    U32,
    Cloud,
    WireError,
    check_finite,
    check_score,
    checked_stamp_ns,
    count_of,
    field_of,
    new_cloud,
    view_cloud,
)
from maem_ros.wire.q4_kernel import decode_pairs

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

    float32 with numba: one pass of the q4_kernel. Otherwise written for speed on a full mesh
    (442k codes, an order of magnitude faster than the obvious expression): cast, then scale
    in place (a multiply that casts on the way is much slower), the origin added to each (u, v)
    pair as one complex number (contiguous rows; a broadcast over pairs has an inner loop of
    length 2; complex addition is the same two float additions), NaN written only when a code
    is missing."""
    if dtype is np.float32 and np.ndim(code) == 2:
        fast = decode_pairs(code, origin if origin is not None else np.zeros((len(code), 2), np.float32))
        if fast is not None:
            return fast
    out: np.ndarray = np.asarray(code).astype(dtype)
    out *= dtype(1.0 / Q4_SCALE)
    if origin is not None and len(out) and out.shape[1]:
        cplx = np.complex64 if out.dtype == np.float32 else np.complex128
        shift = (origin[:, 0] + 1j * origin[:, 1]).astype(cplx)
        pairs: np.ndarray = out.view(cplx)
        pairs += shift[:, None]
    if out.size and code.max() == Q4_MISSING:
        out[code == Q4_MISSING] = np.nan
    return out


def q4_origin(verts2d: np.ndarray) -> np.ndarray:
    """(N, 2) px origin of each detection's q4 codes: the floor of its smallest finite vertex
    coordinates (0 where it has none), an integer so origin + code / 16 is exact in float32."""
    with np.errstate(invalid="ignore"):
        lo = (
            np.nanmin(np.where(np.isfinite(verts2d), verts2d, np.nan), axis=1)
            if verts2d.shape[1]
            else np.zeros((len(verts2d), 2))
        )
    return np.floor(np.nan_to_num(lo, nan=0.0)).astype(np.float32)


def detections_to_cloud(dets: FrameDetections, vertices: str = "f32", keypoints: str = "f32") -> Cloud:
    """FrameDetections -> PointCloud2 layout (a Cloud) (frame_id = camera, stamp = image stamp).

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
    fields = [
        ("bbox", F32, 4),
        ("score", F32, 1),
        (*k_field, 2 * j),
        ("kpts3d", F32, 3 * j),
        (*v_field, 2 * v),
    ]
    if vertices == "q4":
        fields.append((ORIGIN_FIELD, F32, 2))
    if dets.mesh_subset is not None:
        fields.append((SUBSET_FIELD, U32, 3))
    msg, rec = new_cloud(dets.stamp_ns, dets.camera, fields, n)
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
    return msg


def _detection_layout(msg: Any, topic: str) -> dict[str, int]:
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
        raise WireError(
            topic,
            SUBSET_FIELD,
            f"detection {row} announces {sub[row].tolist()}, detection 0 {sub[0].tolist()}",
            "bad_subset",
        )
    mesh, stride, count = (int(x) for x in sub[0])
    if stride < 1 or mesh < v:
        raise WireError(
            topic,
            SUBSET_FIELD,
            f"(mesh {mesh}, stride {stride}, count {count}) for {v} vertices",
            "bad_subset",
        )
    ids = vertex_subset(mesh, stride, count)
    got = mesh if ids is None else ids.size
    if got != v:
        raise WireError(
            topic,
            SUBSET_FIELD,
            f"(mesh {mesh}, stride {stride}, count {count}) selects {got} vertices, verts2d has {v}",
            "bad_subset",
        )
    return mesh, stride, count


@dataclass(frozen=True)
class DetectionsMessage:
    """A detections message checked field by field (layout, counts, finiteness, boxes, scores,
    vertex subset), its small arrays decoded and its vertices still in the message: f32 a view
    of msg.data, q4 the uint16 codes (``origin`` (N, 2) px added on decoding). A receiver can
    queue it, or drop it with its reason, at the cost of the checks, and pay the decoding of
    the mesh vertices (:meth:`decode`) only for the messages it uses.

    bboxes (N, 4) px, scores (N,), kpts2d (N, J, 2) px (NaN = not seen), kpts3d (N, J, 3) m,
    vertices (N, 2V): float32 px or uint16 q4 codes."""

    camera: str
    stamp_ns: int
    bboxes: np.ndarray
    scores: np.ndarray
    kpts2d: np.ndarray
    kpts3d: np.ndarray
    vertices: np.ndarray
    origin: np.ndarray | None
    mesh_subset: tuple[int, int, int] | None
    #: f32 vertices: (smallest, largest) coordinate, u and v together (NaN: none present), as
    #: the finiteness check on reading found them; None for q4 (read from the codes)
    f32_range: tuple[float, float] | None = None

    @property
    def n(self) -> int:
        return len(self.bboxes)

    @property
    def num_vertices(self) -> int:
        return self.vertices.shape[1] // 2 if self.vertices.ndim == 2 else 0

    def vertex_extremes(self, exact: bool = True) -> np.ndarray:
        """(2, 2) px: rows min and max, columns u and v, over the vertices present (NaN where
        none is): enough to bound-check every vertex without decoding them. ``exact=False``:
        bounds that may be wider (each detection's u and v taken together), from reductions
        over contiguous memory only, which are several times faster than per-axis ones."""
        pairs = self.vertices.reshape(self.n, -1, 2)
        if self.vertices.dtype == np.uint16:
            return _q4_extremes(pairs, self.origin) if exact else _q4_bounds(self.vertices, self.origin)
        out = np.full((2, 2), np.nan)
        if not exact and self.f32_range is not None:
            out[0], out[1] = self.f32_range
        elif self.vertices.size:
            for k in range(2):
                out[0, k] = np.fmin.reduce(pairs[..., k], axis=None)
                out[1, k] = np.fmax.reduce(pairs[..., k], axis=None)
        return out

    @property
    def vertices_checked(self) -> bool:
        """Whether the vertices were checked (q4 codes always are; f32 ones unless read with
        ``check_f32_vertices=False``, see :meth:`with_vertex_scan`)."""
        return self.vertices.dtype == np.uint16 or self.f32_range is not None

    def check_vertices(self, topic: str) -> DetectionsMessage:
        """This message with its f32 vertices checked (:func:`read_detections`' check)."""
        if self.vertices_checked:
            return self
        return replace(self, f32_range=_check_f32_vertices(topic, self.vertices))

    def with_vertex_scan(self, topic: str, first_inf: int, low: float, high: float) -> DetectionsMessage:
        """This message with its f32 vertices checked by another pass over them (the pair
        gates' preparation: first detection with an inf, -1 none; smallest and largest
        coordinate present): WireError (nonfinite) as the reading check raises it."""
        if first_inf >= 0:
            raise WireError(topic, "verts2d", f"inf in detection {first_inf}", "nonfinite")
        return replace(self, f32_range=(low, high))

    def decode(self, vertices: bool = True) -> FrameDetections:
        """The FrameDetections (marked validated when everything was checked on reading: the
        f32 vertices unless they were not, see :attr:`vertices_checked`); q4 vertex codes are
        decoded into one float32 array (NaN = missing), f32 ones stay a view. ``vertices``
        False: without the mesh (no vertex, no mesh subset), for a step that reads none."""
        n, v = self.n, self.num_vertices if vertices else 0
        if not vertices:
            verts = np.zeros((n, 0, 2), np.float32)
        elif self.vertices.dtype == np.uint16:
            verts = decode_q4(self.vertices, origin=self.origin)
        else:
            verts = self.vertices
        frame = FrameDetections(
            camera=self.camera,
            stamp_ns=self.stamp_ns,
            bboxes=self.bboxes,
            scores=self.scores,
            kpts2d=self.kpts2d,
            kpts3d=self.kpts3d,
            verts2d=verts.reshape(n, v, 2),
            mesh_subset=self.mesh_subset if vertices else None,
        )
        return frame.mark_validated() if self.vertices_checked or not vertices else frame


def _q4_range_px(low: np.ndarray, high: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """(2, 2) px min/max (u, v) from per-detection (N, 2) or (N, 1) smallest and largest
    present codes (NaN: none present), ``origin`` (N, 2) px added."""
    shift = origin.astype(np.float64) if origin is not None else 0.0
    low, high = low / Q4_SCALE + shift, high / Q4_SCALE + shift
    out = np.full((2, 2), np.nan)
    with np.errstate(invalid="ignore"):
        out[0], out[1] = np.fmin.reduce(low, axis=0), np.fmax.reduce(high, axis=0)
    return out


def _largest_present(codes: np.ndarray, largest: np.ndarray) -> np.ndarray:
    """``largest`` (per row of ``codes``, float) with the missing marker replaced by the
    largest code present in that row (NaN: none): the marker is the largest code, so only
    rows that miss a vertex need a second pass."""
    for row in np.flatnonzero(largest == Q4_MISSING):
        present = codes[row] != Q4_MISSING
        largest[row] = codes[row].max(where=present, initial=0) if present.any() else np.nan
    return largest


def _q4_bounds(codes: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """(2, 2) px bounds (min, max rows; u, v columns) containing every present vertex of the
    q4 ``codes`` (N, 2V): per detection, u and v codes reduced together (contiguous rows)."""
    if codes.size == 0:
        return np.full((2, 2), np.nan)
    low = codes.min(axis=1).astype(np.float64)
    low[low == Q4_MISSING] = np.nan
    high = _largest_present(codes, codes.max(axis=1).astype(np.float64))
    return _q4_range_px(low[:, None], high[:, None], origin)


def _q4_extremes(codes: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """(2, 2) px min/max (u, v) of the q4 vertices ``codes`` (N, V, 2) present."""
    if codes.size == 0:
        return np.full((2, 2), np.nan)
    axes = [codes[..., k] for k in range(2)]
    low = np.stack([a.min(axis=1) for a in axes], axis=1).astype(np.float64)
    low[low == Q4_MISSING] = np.nan
    high = np.stack([_largest_present(a, a.max(axis=1).astype(np.float64)) for a in axes], axis=1)
    return _q4_range_px(low, high, origin)


def _check_f32_vertices(topic: str, verts: np.ndarray) -> tuple[float, float]:
    """The smallest and largest coordinate of float32 vertices (N, 2V) (NaN = missing,
    ignored; NaN when none is present); WireError (nonfinite) naming the detection with an
    inf: two reductions without temporaries, the elementwise check only when an extreme is
    infinite."""
    if not verts.size:
        return np.nan, np.nan
    low, high = float(np.fmin.reduce(verts, axis=None)), float(np.fmax.reduce(verts, axis=None))
    if np.isinf(low) or np.isinf(high):
        check_finite(topic, "verts2d", verts, allow_nan=True)
    return low, high


def _check_counts(topic: str, counts: dict[str, int], kname: str, vname: str) -> int:
    """J (keypoints per detection) from the fields' counts; WireError (bad_count) when they
    disagree with the layout."""
    if counts["bbox"] != 4:
        raise WireError(topic, "bbox", f"count {counts['bbox']}, expected 4", "bad_count")
    if counts["score"] != 1:
        raise WireError(topic, "score", f"count {counts['score']}, expected 1", "bad_count")
    if counts[kname] % 2 or counts[kname] == 0:
        raise WireError(topic, kname, f"count {counts[kname]}, expected 2J (J >= 1)", "bad_count")
    j = counts[kname] // 2
    if counts["kpts3d"] != 3 * j:
        raise WireError(
            topic,
            "kpts3d",
            f"count {counts['kpts3d']}, expected 3J = {3 * j} (J={j} from {kname})",
            "bad_count",
        )
    if counts[vname] % 2:
        raise WireError(topic, vname, f"count {counts[vname]}, expected 2V", "bad_count")
    if ORIGIN_FIELD in counts and counts[ORIGIN_FIELD] != 2:
        raise WireError(
            topic, ORIGIN_FIELD, f"count {counts[ORIGIN_FIELD]}, expected 2 (u v px)", "bad_count"
        )
    if SUBSET_FIELD in counts and counts[SUBSET_FIELD] != 3:
        raise WireError(
            topic,
            SUBSET_FIELD,
            f"count {counts[SUBSET_FIELD]}, expected 3 (mesh vertices, stride, count)",
            "bad_count",
        )
    return j


def _check_camera(
    msg: Any, topic: str, known_cameras: Sequence[str] | None, expected_camera: str | None
) -> str:
    """header.frame_id, checked against the rig's cameras and the topic's camera."""
    cam: str = msg.header.frame_id
    if known_cameras is not None and cam not in known_cameras:
        raise WireError(
            topic,
            "header.frame_id",
            f"unknown camera {cam!r} (rig has {list(known_cameras)})",
            "unknown_camera",
        )
    if expected_camera is not None and cam != expected_camera:
        raise WireError(
            topic,
            "header.frame_id",
            f"camera {cam!r} on the topic of camera {expected_camera!r}",
            "camera_mismatch",
        )
    return cam


def read_detections(
    msg: Any,
    topic: str,
    known_cameras: Sequence[str] | None = None,
    expected_camera: str | None = None,
    check_f32_vertices: bool = True,
) -> DetectionsMessage:
    """PointCloud2 -> DetectionsMessage, every field checked (WireError with the reason), the
    mesh vertices left undecoded.

    ``known_cameras``: frame_id must be one of them; ``expected_camera``: frame_id must equal it
    (the camera whose topic this came from). ``check_f32_vertices=False``: f32 vertices are
    left for a pass the receiver makes over them anyway (DetectionsMessage.with_vertex_scan,
    or check_vertices); a q4 message is checked whole regardless.
    """
    cam = _check_camera(msg, topic, known_cameras, expected_camera)
    layout = _detection_layout(msg, topic)
    rec = view_cloud(msg, topic, layout)
    kname = "kpts2d_q4" if "kpts2d_q4" in layout else "kpts2d"
    vname = "verts2d_q4" if "verts2d_q4" in layout else "verts2d"
    j = _check_counts(topic, {name: count_of(msg, name) for name in layout}, kname, vname)
    n = len(rec)
    fields = {name: field_of(rec, name) for name in layout}
    for name in ("bbox", "score", "kpts3d"):
        check_finite(topic, name, fields[name])
    if kname == "kpts2d_q4":  # 65535 = keypoint missing (NaN), as for vertices
        kpts2d = decode_q4(fields[kname], np.float64)
    else:
        check_finite(topic, "kpts2d", fields["kpts2d"], allow_nan=True)  # NaN = not seen
        kpts2d = fields["kpts2d"]
    origin = fields.get(ORIGIN_FIELD)
    if origin is not None:
        check_finite(topic, ORIGIN_FIELD, origin)
    # a q4 code is never inf; NaN = missing f32 vertex
    f32_range = (
        _check_f32_vertices(topic, fields[vname]) if vname == "verts2d" and check_f32_vertices else None
    )
    bbox = fields["bbox"]
    inverted = (bbox[:, 2] < bbox[:, 0]) | (bbox[:, 3] < bbox[:, 1])
    if inverted.any():
        raise WireError(
            topic,
            "bbox",
            f"inverted box (x2<x1 or y2<y1) in detection {int(np.argmax(inverted))}",
            "inverted_bbox",
        )
    check_score(topic, fields["score"][:, 0], "detection")
    subset = (
        _mesh_subset(topic, fields[SUBSET_FIELD], fields[vname].shape[1] // 2)
        if SUBSET_FIELD in layout and n
        else None
    )
    return DetectionsMessage(
        camera=cam,
        stamp_ns=checked_stamp_ns(msg.header.stamp, topic),
        bboxes=bbox,
        scores=fields["score"][:, 0],
        kpts2d=kpts2d.reshape(n, j, 2),
        kpts3d=fields["kpts3d"].reshape(n, j, 3),
        vertices=fields[vname],
        origin=origin,
        mesh_subset=subset,
        f32_range=f32_range,
    )


def msg_to_detections(
    msg: Any, topic: str, known_cameras: Sequence[str] | None = None, expected_camera: str | None = None
) -> FrameDetections:
    """PointCloud2 -> FrameDetections, validated once (read_detections, then decoded; the
    result is marked validated, so the association does not check the arrays again); f32
    verts2d is a view of msg.data, q4 codes are decoded once into one float32 array (NaN =
    missing)."""
    return read_detections(msg, topic, known_cameras, expected_camera).decode()


def detections_to_msg(dets: FrameDetections, vertices: str = "f32", keypoints: str = "f32") -> Any:
    """detections_to_cloud as a rosbags sensor_msgs/PointCloud2 (for a bag writer)."""
    return to_rosbags(detections_to_cloud(dets, vertices, keypoints))
