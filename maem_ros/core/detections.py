"""Per-camera, per-frame person detections as the frontend delivers them.

All 2D coordinates are in the RECTIFIED pinhole image of the camera (px);
3D keypoints are in metres in the detection's own camera-relative frame (the
association only compares them up to a similarity transform).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import cast

import numpy as np

from maem_ros.core.errors import InputError


@lru_cache(maxsize=32)
def vertex_subset(num_vertices: int, stride: int = 1, count: int = 0) -> np.ndarray | None:
    """Indices of the vertices the mesh gate uses, or None for all of them.

    Every ``stride``-th vertex; then, if ``0 < count`` < that many, ``count`` of them spread
    evenly over the index range (fixed topology: the same spots in every detection).
    """
    if stride == 1 and (count <= 0 or count >= num_vertices):
        return None
    idx = np.arange(0, num_vertices, stride, dtype=np.int64)
    if 0 < count < idx.size:
        idx = idx[np.unique(np.linspace(0, idx.size - 1, count).round().astype(np.int64))]
    idx.setflags(write=False)
    return idx


def _subset_vertex_ids(mesh_subset: tuple[int, int, int]) -> np.ndarray:
    """Full-mesh index of each verts2d column (sorted) under ``mesh_subset`` = (mesh vertices,
    stride, count) (FrameDetections.mesh_subset)."""
    ids = vertex_subset(*mesh_subset)
    return np.arange(mesh_subset[0]) if ids is None else ids


@dataclass
class FrameDetections:
    """N detections of one camera at one stamp (J keypoints, V mesh vertices each).

    bboxes (N,4) x1 y1 x2 y2 px; scores (N,); kpts2d (N,J,2) px (NaN = keypoint not seen, e.g.
    under the estimator's visibility threshold); kpts3d (N,J,3) m;
    verts2d (N,V,2) px, float32 (V may be 0 when no mesh is available; NaN = vertex missing,
    e.g. outside what the compact wire layout can carry). ``stamp_ns`` is the image capture
    time in integer nanoseconds. ``mesh_subset`` = (mesh vertices, stride, count) when verts2d
    holds the fixed-topology subset vertex_subset(*mesh_subset) of the mesh
    (announced on the wire), None when it holds the whole mesh.
    """

    camera: str
    stamp_ns: int
    bboxes: np.ndarray
    scores: np.ndarray
    kpts2d: np.ndarray
    kpts3d: np.ndarray
    verts2d: np.ndarray
    mesh_subset: tuple[int, int, int] | None = None
    #: what :meth:`validate` (or the decoder, :meth:`mark_validated`) checked: the camera, the
    #: subset and the very array objects (held, compared by identity: an array replaced since
    #: is checked again, and a held array's id cannot be reused by another)
    _validated: tuple = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.bboxes = np.asarray(self.bboxes, dtype=np.float64)
        self.scores = np.asarray(self.scores, dtype=np.float64)
        self.kpts2d = np.asarray(self.kpts2d, dtype=np.float64)
        self.kpts3d = np.asarray(self.kpts3d, dtype=np.float64)
        self.verts2d = np.asarray(self.verts2d, dtype=np.float32)
        self.stamp_ns = int(self.stamp_ns)
        if self.mesh_subset is not None:
            # a subset of the wrong length is kept as given: validate() names it
            self.mesh_subset = cast(tuple[int, int, int], tuple(int(v) for v in self.mesh_subset))

    @property
    def n(self) -> int:
        return int(self.bboxes.shape[0]) if self.bboxes.ndim == 2 else 0

    @property
    def num_joints(self) -> int:
        return int(self.kpts2d.shape[1]) if self.kpts2d.ndim == 3 else 0

    @property
    def num_vertices(self) -> int:
        return int(self.verts2d.shape[1]) if self.verts2d.ndim == 3 else 0

    @property
    def mesh_vertices(self) -> int:
        """Vertices of the full mesh (verts2d may hold a subset of them)."""
        return self.mesh_subset[0] if self.mesh_subset is not None else self.num_vertices

    @property
    def vertex_ids(self) -> np.ndarray | None:
        """Full-mesh index of each verts2d column (sorted), None when verts2d is the whole mesh."""
        return None if self.mesh_subset is None else _subset_vertex_ids(self.mesh_subset)

    @property
    def centers(self) -> np.ndarray:
        """(N,2) bbox centres, rectified px."""
        return 0.5 * (self.bboxes[:, :2] + self.bboxes[:, 2:])

    @classmethod
    def empty(cls, camera: str, stamp_ns: int, num_joints: int, num_vertices: int) -> FrameDetections:
        return cls(
            camera,
            stamp_ns,
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros((0, num_joints, 2)),
            np.zeros((0, num_joints, 3)),
            np.zeros((0, num_vertices, 2), np.float32),
        )

    def select(self, index: np.ndarray) -> FrameDetections:
        """Subset by boolean mask or integer index (copies); validated when self is (every
        check of :meth:`validate` is per detection or on shapes the subset keeps)."""
        out = FrameDetections(
            self.camera,
            self.stamp_ns,
            self.bboxes[index],
            self.scores[index],
            self.kpts2d[index],
            self.kpts3d[index],
            self.verts2d[index],
            self.mesh_subset,
        )
        if self._is_validated():
            out.mark_validated()
        return out

    def with_vertex_subset(self, stride: int = 1, count: int = 0) -> FrameDetections:
        """These detections with verts2d cut to the fixed-topology subset
        ``vertex_subset(mesh_vertices, stride, count)``, announced in mesh_subset
        (self when verts2d holds exactly those already). ValueError when verts2d lacks some of
        them (it holds a different subset)."""
        mesh = self.mesh_vertices
        want = vertex_subset(mesh, int(stride), int(count))
        have = self.vertex_ids
        if want is None:
            if have is not None:
                raise ValueError(
                    f"detections of camera {self.camera!r}: verts2d: holds the "
                    f"subset {self.mesh_subset}, the whole mesh was asked for"
                )
            return self
        if have is not None and np.array_equal(have, want):
            return self
        cols = want if have is None else np.searchsorted(have, want)
        if have is not None and (
            cols.max(initial=0) >= have.size
            or not np.array_equal(have[np.minimum(cols, have.size - 1)], want)
        ):
            raise ValueError(
                f"detections of camera {self.camera!r}: verts2d: subset "
                f"{self.mesh_subset} does not contain (stride {stride}, count {count})"
            )
        return FrameDetections(
            self.camera,
            self.stamp_ns,
            self.bboxes,
            self.scores,
            self.kpts2d,
            self.kpts3d,
            np.ascontiguousarray(self.verts2d[:, cols]),
            (mesh, int(stride), int(count)),
        )

    def _arrays(self) -> tuple:
        return (
            self.camera,
            self.mesh_subset,
            self.bboxes,
            self.scores,
            self.kpts2d,
            self.kpts3d,
            self.verts2d,
        )

    def _is_validated(self) -> bool:
        """Whether the fields are the objects :meth:`mark_validated` / :meth:`validate` saw
        (arrays by identity, of the shapes they had)."""
        token, now = self._validated, self._arrays()
        return (
            len(token) == len(now) + 1
            and token[0] == now[0]
            and token[1] == now[1]
            and all(a is b for a, b in zip(token[2:], now[2:]))
            and token[-1] == tuple(a.shape for a in now[2:])
        )

    def mark_validated(self) -> FrameDetections:
        """Record that the caller (the wire decoder) checked everything :meth:`validate` checks,
        so consumers do not check the same arrays twice. Replacing an array re-enables the
        check; writing into the arrays in place afterwards is the writer's responsibility."""
        self._validated = self._token()
        return self

    def _token(self) -> tuple:
        arrays = self._arrays()
        return arrays + (tuple(a.shape for a in arrays[2:]),)

    def validate(self, known_cameras: Iterable[str] | None = None) -> FrameDetections:
        """Raise InputError (a ValueError, with a reason) naming the first bad field; return self
        when valid."""
        where = f"detections of camera {self.camera!r}"
        if known_cameras is not None and self.camera not in set(known_cameras):
            raise ValueError(f"{where}: camera: unknown camera {self.camera!r}")
        if self._is_validated():
            return self
        if self.bboxes.ndim != 2 or self.bboxes.shape[1] != 4:
            raise InputError(f"{where}: bbox: expected shape (N,4), got {self.bboxes.shape}", "bad_count")
        n = self.bboxes.shape[0]
        _check_shape(where, "score", self.scores, (n,))
        if self.kpts2d.ndim != 3 or self.kpts2d.shape[0] != n or self.kpts2d.shape[2] != 2:
            raise InputError(
                f"{where}: kpts2d: expected shape ({n},J,2), got {self.kpts2d.shape}", "bad_count"
            )
        j = self.kpts2d.shape[1]
        _check_shape(where, "kpts3d", self.kpts3d, (n, j, 3))
        if self.verts2d.ndim != 3 or self.verts2d.shape[0] != n or self.verts2d.shape[2] != 2:
            raise ValueError(f"{where}: verts2d: expected shape ({n},V,2), got {self.verts2d.shape}")
        if self.mesh_subset is not None:
            ids = _subset_vertex_ids(self.mesh_subset)
            if len(self.mesh_subset) != 3 or ids.size != self.verts2d.shape[1]:
                raise ValueError(
                    f"{where}: mesh_subset: {self.mesh_subset} selects {ids.size} "
                    f"vertices, verts2d has {self.verts2d.shape[1]}"
                )
        for name, arr in (
            ("bbox", self.bboxes),
            ("score", self.scores),
            ("kpts2d", self.kpts2d),
            ("kpts3d", self.kpts3d),
            ("verts2d", self.verts2d),
        ):
            # a missing vertex or keypoint (not seen) is NaN; inf is never a coordinate
            missing_ok = name in ("verts2d", "kpts2d")
            bad = np.isinf(arr) if missing_ok else ~np.isfinite(arr)
            if bad.any():
                det = int(np.argwhere(bad)[0][0]) if arr.ndim > 1 else int(np.argmax(bad))
                what = "inf" if missing_ok else "NaN or inf"
                raise ValueError(f"{where}: {name}: {what} in detection {det}")
        inverted = (self.bboxes[:, 2] < self.bboxes[:, 0]) | (self.bboxes[:, 3] < self.bboxes[:, 1])
        if inverted.any():
            raise InputError(
                f"{where}: bbox: inverted box (x2<x1 or y2<y1) in detection {int(np.argmax(inverted))}",
                "inverted_bbox",
            )
        if np.any((self.scores < 0) | (self.scores > 1)):
            raise ValueError(
                f"{where}: score: outside [0, 1] in detection "
                f"{int(np.argmax((self.scores < 0) | (self.scores > 1)))}"
            )
        self._validated = self._token()
        return self


def _check_shape(where: str, field: str, arr: np.ndarray, shape: tuple[int, ...]) -> None:
    if arr.shape != shape:
        raise InputError(f"{where}: {field}: expected shape {shape}, got {arr.shape}", "bad_count")


@dataclass
class Cluster:
    """One person: members (M,2) int64 (camera index in rig order, detection index in that
    camera's FrameDetections as given), sorted; costs (M,) mean pose cost (m) of each member to
    the rest of the cluster, NaN if alone.
    """

    members: np.ndarray
    costs: np.ndarray

    def __post_init__(self) -> None:
        self.members = np.asarray(self.members, dtype=np.int64).reshape(-1, 2)
        self.costs = np.asarray(self.costs, dtype=np.float64).reshape(-1)

    def __len__(self) -> int:
        return int(self.members.shape[0])


@dataclass
class DetectionTable:
    """The detections of one frame set in one flat table: cameras in rig order, concatenated.

    Row r is detection ``det[r]`` of camera index ``cam[r]``; the rows of camera c are
    ``offsets[c]:offsets[c + 1]`` (empty for an absent camera). The one id scheme of a frame
    set inside association and triangulation: a row index. Small per-detection arrays are
    concatenated (scores (N,), centers (N,2) px, kpts2d (N,J,2) rectified px, kpts3d (N,J,3) m);
    the mesh vertices stay in the per-camera ``frames`` (the epipolar kernel reads them there,
    without a copy).
    """

    cam: np.ndarray
    det: np.ndarray
    offsets: np.ndarray
    scores: np.ndarray
    centers: np.ndarray
    kpts2d: np.ndarray
    kpts3d: np.ndarray
    frames: dict[int, FrameDetections]

    @classmethod
    def build(
        cls, frames: dict[int, FrameDetections], num_cameras: int, keep: dict[int, np.ndarray] | None = None
    ) -> DetectionTable:
        """Table of ``frames`` (keyed by camera index); ``keep[c]`` = detection indices to take
        (default: all), in increasing order."""
        cams = sorted(frames)
        idx = {c: (np.arange(frames[c].n) if keep is None else np.asarray(keep[c], np.int64)) for c in cams}
        sizes = np.zeros(num_cameras, np.int64)
        for c in cams:
            sizes[c] = idx[c].size
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        J = next((frames[c].num_joints for c in cams if frames[c].n), 0)

        def cat(get, shape):
            # every detection kept (increasing, distinct: all of them): the array itself, not a
            # gathered copy that concatenate would copy again
            parts = [
                get(frames[c]) if idx[c].size == frames[c].n else get(frames[c])[idx[c]]
                for c in cams
                if idx[c].size
            ]
            return np.concatenate(parts) if parts else np.zeros((0,) + shape)

        return cls(
            cam=np.repeat(np.arange(num_cameras), sizes),
            det=np.concatenate([idx[c] for c in cams] or [np.zeros(0, np.int64)]).astype(np.int64),
            offsets=offsets,
            scores=cat(lambda f: f.scores, ()),
            centers=cat(lambda f: f.centers, (2,)),
            kpts2d=cat(lambda f: f.kpts2d, (J, 2)),
            kpts3d=cat(lambda f: f.kpts3d, (J, 3)),
            frames=frames,
        )

    def __len__(self) -> int:
        return int(self.cam.size)

    @property
    def num_joints(self) -> int:
        return int(self.kpts2d.shape[1])

    def rows(self, members: np.ndarray) -> np.ndarray:
        """Row indices of (camera index, detection index) members (M,2); ValueError if absent."""
        members = np.asarray(members, np.int64).reshape(-1, 2)
        # rows are sorted by (camera, detection): one searchsorted on a combined key
        span = int(max(self.det.max(initial=0), members[:, 1].max(initial=0))) + 1
        key = self.cam * span + self.det
        want = members[:, 0] * span + members[:, 1]
        pos = np.searchsorted(key, want)
        if np.any(pos >= len(self)) or np.any(key[np.minimum(pos, max(len(self) - 1, 0))] != want):
            raise ValueError("members: detection not in the table")
        return pos

    def members(self, rows: np.ndarray) -> np.ndarray:
        """(M,2) (camera index, detection index) of table rows."""
        return np.stack([self.cam[rows], self.det[rows]], axis=1)


#: PairSet.stage values: passed everything, or the first stage that rejected the pair
PASSED, REJECTED_REPROJ, REJECTED_EPIPOLAR, REJECTED_COST = 0, 1, 2, 3


@dataclass
class PairSet:
    """Every pair of kept detections of different cameras (rows i < j of the DetectionTable,
    camera of i < camera of j), flat over all camera pairs in order.

    stage: PASSED or the first gate that rejected the pair; pose (m) PA-MPJPE on the cost
    joints and epi (px) mean epipolar distance, both NaN where not computed (rejected
    earlier; epi also where no epipolar gate ran); cost (m) = pose + w * epi where computed.
    """

    i: np.ndarray
    j: np.ndarray
    stage: np.ndarray
    pose: np.ndarray
    epi: np.ndarray
    cost: np.ndarray

    def __len__(self) -> int:
        return int(self.i.size)

    @property
    def passed(self) -> np.ndarray:
        """(S,) passed the gates and the cost cap."""
        return self.stage == PASSED

    @property
    def geometric(self) -> np.ndarray:
        """(S,) passed the geometric gates (the cost cap may still have rejected it)."""
        return (self.stage == PASSED) | (self.stage == REJECTED_COST)


def camera_pair_groups(ca: np.ndarray, cb: np.ndarray):
    """(a, b, indices) per camera pair, in order (pairs are sorted by camera pair)."""
    if ca.size == 0:
        return
    key = ca * 65536 + cb
    bounds = np.flatnonzero(np.diff(key)) + 1
    for idx in np.split(np.arange(ca.size), bounds):
        yield int(ca[idx[0]]), int(cb[idx[0]]), idx
