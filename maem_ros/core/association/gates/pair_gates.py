"""The pair gates behind one interface: :class:`PairGates` of a rig under one set of association
params, with two steps.

- ``prepare(frame)``, once per camera frame as it arrives (the association node calls it
  where it decodes a message, off the frame set's critical path): the mesh gate's screening
  subsets of the frame's vertices copied contiguous and their block ranges, kept by the gates
  (a cache keyed by the frame object, dropped with it), never on the frame itself.
- ``frame_set(frames).decide(pairs)``, per frame set: the bbox-centre reprojection gate and
  the epipolar gate (dense mesh or 2D keypoints) of detection pairs, returning each pair's
  stage (passed, or the gate that rejected it) and mean epipolar distance.

The cross-view association (core.association.pipeline) and the track-assisted association
(core.tracking.temporal) both gate their pairs here; a frame that was not prepared is gated
the same way (its subsets read in place), only slower.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Mapping
from typing import NamedTuple, Protocol

import numpy as np

from maem_ros.core.association.gates.epipolar import PointRows, point_rows
from maem_ros.core.association.gates.execution import ExecutionParams
from maem_ros.core.association.gates.reprojection import (
    BOUND_MARGIN,
    enumerate_pairs,
    reprojection_kernel,
    reprojection_ok,
)
from maem_ros.core.association.gates.rig_geometry import RigGeometry, rig_geometry
from maem_ros.core.association.gates.screening import frame_screened_means, screen_copies, screen_rows
from maem_ros.core.detections import (
    PASSED,
    REJECTED_EPIPOLAR,
    REJECTED_REPROJ,
    DetectionTable,
    FrameDetections,
    vertex_subset,
)
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.jit import have_numba

#: epipolar gate modes: mesh vertices, 2D keypoints, or none
EPIPOLAR_GATES = ("mesh", "sparse", "none")


class GateParams(Protocol):
    """The association params the gates read (core.association.AssociationParams)."""

    tau_reproj_bbox: float
    tau_mesh: float
    reproj_gate: bool
    reproj_reduce: str
    epipolar_gate: str
    epipolar_distance: str
    vertex_stride: int
    vertex_count: int
    execution: ExecutionParams


class GateDecisions(NamedTuple):
    """The gates' verdict on S detection pairs."""

    #: (S,) int8: PASSED, REJECTED_REPROJ or REJECTED_EPIPOLAR (core.detections)
    stage: np.ndarray
    #: (S,) px mean epipolar distance of the pairs that passed the epipolar gate, NaN elsewhere
    epi: np.ndarray
    #: fraction of the pairs' gate points the epipolar gate summed (early exit, screening)
    points_fraction: float


class VertexScan(NamedTuple):
    """What :meth:`PairGates.prepare_scanning`'s pass found over a frame's vertices."""

    #: the first detection with an infinite coordinate (-1: none; NaN = missing is allowed)
    first_inf: int
    #: px, smallest and largest coordinate present, u and v together (NaN: none present)
    low: float
    high: float


class _Prepared(NamedTuple):
    """What ``prepare`` made of one frame: valid while the frame holds ``verts``."""

    verts: np.ndarray
    copies: dict[int, np.ndarray]  # {stride: (N,m,2) float32}: each screening subset, contiguous
    ranges: dict[int, np.ndarray]  # {stride: (N,blocks,2) float32}: PointRows.ranges, 1 = verts


class _PreparedFrames:
    """Prepared frames keyed by the FrameDetections object: each entry holds a weak reference
    to its frame and is removed when the frame is collected (so a later object that reuses the
    address never finds it), and is used only while the frame still holds the vertex array it
    was made from."""

    def __init__(self) -> None:
        self._entries: dict[int, tuple[weakref.ref, _Prepared]] = {}

    def put(self, frame: FrameDetections, prepared: _Prepared) -> None:
        key, entries = id(frame), self._entries

        def drop(ref: weakref.ref, key: int = key) -> None:
            if entries.get(key, (None,))[0] is ref:
                del entries[key]

        entries[key] = (weakref.ref(frame, drop), prepared)

    def get(self, frame: FrameDetections) -> _Prepared | None:
        entry = self._entries.get(id(frame))
        if entry is None or entry[0]() is not frame or entry[1].verts is not frame.verts2d:
            return None
        return entry[1]

    def __len__(self) -> int:
        return len(self._entries)


class PairGates:
    """The reprojection and epipolar gates of ``rig`` under ``params`` (module docstring).

    ``epipolar_gate``: the epipolar gate's mode when it differs from params.epipolar_gate
    (the track stage verifies its clusters on 2D keypoints by default); see
    :meth:`with_epipolar_gate`, which shares the prepared frames.
    """

    def __init__(
        self,
        rig: Rig,
        params: GateParams,
        epipolar_gate: str | None = None,
        prepared: _PreparedFrames | None = None,
    ):
        mode = params.epipolar_gate if epipolar_gate is None else epipolar_gate
        if mode not in EPIPOLAR_GATES:
            raise ValueError(f"epipolar_gate: expected one of {list(EPIPOLAR_GATES)}, got {mode!r}")
        self.rig, self.params, self.epipolar_gate = rig, params, mode
        self.execution: ExecutionParams = params.execution
        self._prepared = _PreparedFrames() if prepared is None else prepared

    def with_epipolar_gate(self, mode: str) -> PairGates:
        """The same gates with the epipolar gate in ``mode`` (mesh | sparse | none), reading
        the frames prepared by this one."""
        return PairGates(self.rig, self.params, mode, self._prepared)

    @property
    def geometry(self) -> RigGeometry:
        """The rig's projections and fundamental matrices (cached per rig)."""
        return rig_geometry(self.rig)

    # -- per camera frame --------------------------------------------------------------
    def prepare(self, frame: FrameDetections) -> FrameDetections:
        """Make the mesh gate's per-frame data of ``frame`` now (one pass over its vertices:
        the screening subsets copied contiguous, the block ranges of the vertices and of the
        copies) and keep it for the frame sets the frame takes part in. Returns the frame.
        Nothing to do (and nothing kept) when the gate would not read it: no mesh gate, a
        vertex subset chosen by the params, the numpy backend, or no screening."""
        strides = self.prepare_strides()
        if strides and frame.n:
            n, v = frame.verts2d.shape[:2]
            made = screen_copies(frame.verts2d.reshape(n, v, 2), strides)
            self._prepared.put(frame, _Prepared(frame.verts2d, made.copies, made.block_ranges))
        return frame

    def prepare_scanning(self, frame: FrameDetections) -> VertexScan | None:
        """:meth:`prepare` for a frame whose vertices nobody has checked yet: the preparing
        pass reads every vertex anyway, so it also says whether one is infinite and what the
        extremes are (a receiver checks the frame at the cost of that one pass). None when
        prepare makes no pass over this frame (its vertices are checked elsewhere, or it has
        none). A frame with an infinite vertex is not kept."""
        strides = self.prepare_strides()
        if not strides or not frame.n:
            return None
        n, v = frame.verts2d.shape[:2]
        made = screen_copies(frame.verts2d.reshape(n, v, 2), strides)
        if made.first_inf < 0:
            self._prepared.put(frame, _Prepared(frame.verts2d, made.copies, made.block_ranges))
        return VertexScan(made.first_inf, *made.extremes)

    def select(self, frame: FrameDetections, index: np.ndarray) -> FrameDetections:
        """``frame.select(index)`` with the rows of what :meth:`prepare` made of the frame."""
        out = frame.select(index)
        made = self._prepared.get(frame)
        if made is not None:
            self._prepared.put(
                out,
                _Prepared(
                    out.verts2d,
                    {s: a[index] for s, a in made.copies.items()},
                    {s: a[index] for s, a in made.ranges.items()},
                ),
            )
        return out

    def is_prepared(self, frame: FrameDetections) -> bool:
        """Whether :meth:`prepare` made data for the frame as it is now."""
        return self._prepared.get(frame) is not None

    @property
    def prepared_frames(self) -> int:
        """Frames whose prepared data the gates hold (each entry goes with its frame)."""
        return len(self._prepared)

    def prepare_strides(self) -> tuple[int, ...]:
        """The screening strides whose subsets ``prepare`` copies: those of the screening
        levels when the numba gate compares every vertex a camera sends, else none (the gate
        would not read them; the numpy backend reads the subsets in place)."""
        p, e = self.params, self.execution
        if (
            self.epipolar_gate != "mesh"
            or p.vertex_stride != 1
            or p.vertex_count > 0
            or e.backend == "numpy"
            or not have_numba()
        ):
            return ()
        return tuple(stride for stride, _ in e.screen_levels())

    # -- per frame set -------------------------------------------------------------------
    def candidates(self, table: DetectionTable) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(i, j, reprojection ok (S,) bool or None when the gate is off) of every pair of
        table rows of different cameras (reprojection.enumerate_pairs' order): with numba
        the enumeration and the reprojection gate are one pass; pass ok to
        :meth:`FrameSet.decide` as ``reprojected``."""
        geometry = self.geometry
        p = self.params
        kernel = reprojection_kernel(self.execution.backend) if p.reproj_gate else None
        if kernel is not None:
            return kernel(
                table.offsets,
                geometry.stack,
                geometry.P[table.cam],
                table.centers,
                float(p.tau_reproj_bbox),
                BOUND_MARGIN,
                p.reproj_reduce == "max",
            )
        i, j = enumerate_pairs(table.offsets)
        ok = (
            reprojection_ok(
                geometry.stack, geometry.P, table.cam, table.centers, i, j, p.tau_reproj_bbox, p.reproj_reduce
            )
            if p.reproj_gate and i.size
            else None
        )
        return i, j, ok

    def frame_set(self, frames: Mapping[int, FrameDetections]) -> FrameSet:
        """The gates of one frame set (frames keyed by camera index in the rig)."""
        return FrameSet(self, dict(frames))

    def camera_points(
        self, frame: FrameDetections, columns: np.ndarray | None
    ) -> tuple[PointRows, list[PointRows | None]]:
        """One camera's points for the epipolar gate (the verts2d ``columns``, None = all, or
        the 2D keypoints) and their screening subsets (coarse to fine; None = too few
        points): what :meth:`prepare` made where it did, else read in place."""
        if self.epipolar_gate == "sparse":
            return point_rows(frame.kpts2d), []
        made = self._prepared.get(frame) if columns is None else None
        if columns is None:
            full = point_rows(frame.verts2d, made.ranges.get(1) if made else None)
        else:
            full = point_rows(frame.verts2d[:, columns])
        subsets: list[PointRows | None] = []
        for stride, _ in self.execution.screen_levels():
            copy = made.copies.get(stride) if made else None
            subsets.append(
                screen_rows(full, stride)
                if copy is None or made is None
                else point_rows(copy, made.ranges.get(stride))
            )
        return full, subsets


class FrameSet:
    """The gates of one frame set: the gate points of each camera made on first use and kept
    for every :meth:`decide` on this frame set (the track stage decides its pairs in two
    passes)."""

    def __init__(self, gates: PairGates, frames: dict[int, FrameDetections]):
        self.gates, self.frames = gates, frames
        self._columns: dict[int, np.ndarray | None] | None = None
        self._points: dict[int, tuple[PointRows, list[PointRows | None]]] = {}
        self._views: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def decide(
        self,
        cam_a: np.ndarray,
        det_a: np.ndarray,
        cam_b: np.ndarray,
        det_b: np.ndarray,
        reprojected: np.ndarray | None = None,
    ) -> GateDecisions:
        """The gates of the S pairs (detection det_a[s] of camera cam_a[s], det_b[s] of
        cam_b[s]; cam_a < cam_b). ``reprojected``: the reprojection gate's decisions when
        already made (:meth:`PairGates.candidates`), else the gate runs here (when on)."""
        pairs = tuple(np.asarray(v, np.int64) for v in (cam_a, det_a, cam_b, det_b))
        if reprojected is None and self.gates.params.reproj_gate and pairs[0].size:
            reprojected = self._reprojection(*pairs)
        return self._decide(pairs[0].size, reprojected, lambda alive: tuple(v[alive] for v in pairs))

    def decide_rows(
        self, table: DetectionTable, i: np.ndarray, j: np.ndarray, reprojected: np.ndarray | None
    ) -> GateDecisions:
        """:meth:`decide` of the pairs of table rows (i, j) (:meth:`PairGates.candidates`),
        the rows' cameras and detections looked up for the reprojection survivors only."""
        if reprojected is None and self.gates.params.reproj_gate and i.size:
            return self.decide(table.cam[i], table.det[i], table.cam[j], table.det[j])
        return self._decide(
            i.size,
            reprojected,
            lambda alive: (
                table.cam[i[alive]],
                table.det[i[alive]],
                table.cam[j[alive]],
                table.det[j[alive]],
            ),
        )

    def _decide(
        self, S: int, reprojected: np.ndarray | None, pairs_of: Callable[[np.ndarray], tuple[np.ndarray, ...]]
    ) -> GateDecisions:
        """Stages and means of S pairs after the reprojection gate's decisions (None: off);
        pairs_of(alive) -> (cam_a, det_a, cam_b, det_b) of the pairs alive (indices)."""
        if reprojected is not None:  # masks over every pair, not index arrays
            stage = np.where(reprojected, np.int8(PASSED), np.int8(REJECTED_REPROJ))
            alive = np.flatnonzero(reprojected)
        else:
            stage = np.full(S, PASSED, np.int8)
            alive = np.arange(S)
        epi = np.full(S, np.nan)
        fraction = 0.0
        if self.gates.epipolar_gate != "none" and alive.size:
            keep, mean, fraction = self._epipolar(*pairs_of(alive))
            epi[alive] = mean
            stage[alive[~keep]] = REJECTED_EPIPOLAR
        return GateDecisions(stage, epi, fraction)

    def _reprojection(
        self, cam_a: np.ndarray, det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray
    ) -> np.ndarray:
        """(S,) reprojection gate of the pairs, over every detection of the frame set."""
        if self._views is None:
            cams = sorted(self.frames)
            sizes = np.zeros(max(cams, default=-1) + 1, np.int64)
            for c in cams:
                sizes[c] = self.frames[c].n
            offsets = np.concatenate([[0], np.cumsum(sizes)])
            centers = np.concatenate([self.frames[c].centers for c in cams]) if cams else np.zeros((0, 2))
            self._views = offsets, np.repeat(np.arange(sizes.size), sizes), centers
        offsets, cam, centers = self._views
        geometry, p = self.gates.geometry, self.gates.params
        return reprojection_ok(
            geometry.stack,
            geometry.P,
            cam,
            centers,
            offsets[cam_a] + det_a,
            offsets[cam_b] + det_b,
            p.tau_reproj_bbox,
            p.reproj_reduce,
        )

    def _epipolar(
        self, cam_a: np.ndarray, det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """(keep, mean px exact where kept, fraction of the gate points summed) of pairs."""
        p, e = self.gates.params, self.gates.execution
        cams = np.unique(np.concatenate([cam_a, cam_b])).tolist()
        rows = {c: self.points(c) for c in cams}
        full = {c: r[0] for c, r in rows.items()}
        levels = []  # the screening levels every camera taking part has a subset for
        for k, (_, margin) in enumerate(e.screen_levels()):
            subsets = {c: r[1][k] if k < len(r[1]) else None for c, r in rows.items()}
            present = {c: v for c, v in subsets.items() if v is not None}
            if len(present) == len(subsets):
                levels.append((present, margin))
        # one kernel call for every camera pair of the frame (per level): a detection's block
        # is read once from memory for all its candidate pairs
        keep, mean, evaluated = frame_screened_means(
            full,
            levels,
            self.gates.geometry.pairs,
            cam_a,
            det_a,
            cam_b,
            det_b,
            p.tau_mesh,
            symmetric=p.epipolar_distance == "symmetric",
            early_exit=e.early_exit,
            backend=e.backend,
            precision=e.epipolar_precision,
        )
        budget = cam_a.size * full[cams[0]].n
        return keep, mean, evaluated / budget if budget else 0.0

    def points(self, c: int) -> tuple[PointRows, list[PointRows | None]]:
        """Camera c's gate points and screening subsets (:meth:`PairGates.camera_points`)."""
        hit = self._points.get(c)
        if hit is None:
            if self._columns is None:
                self._columns = (
                    gate_columns(self.frames, self.gates.params) if self.gates.epipolar_gate == "mesh" else {}
                )
            hit = self._points[c] = self.gates.camera_points(self.frames[c], self._columns.get(c))
        return hit


def gate_columns(frames: Mapping[int, FrameDetections], params: GateParams) -> dict[int, np.ndarray | None]:
    """Per camera, the verts2d columns the mesh gate uses (None = all of them, no copy).

    The gate compares full-mesh vertex ids: the ones the params select (vertex_stride /
    vertex_count on the full mesh) that every camera with detections sent (a frontend may send
    an announced subset, FrameDetections.vertex_ids).
    """
    live = {c: fd for c, fd in frames.items() if fd.n}
    if not live:
        return {c: None for c in frames}
    mesh = next(iter(live.values())).mesh_vertices
    wanted = vertex_subset(mesh, params.vertex_stride, params.vertex_count)
    ids = {c: fd.vertex_ids for c, fd in live.items()}
    common = wanted
    for got in ids.values():
        if got is not None:
            common = got if common is None else np.intersect1d(common, got, assume_unique=True)
    if common is None:
        return {c: None for c in frames}
    out: dict[int, np.ndarray | None] = {c: None for c in frames}
    for c in live:
        got = ids[c]
        if got is None:
            out[c] = None if common.size == mesh else common
        elif got.size != common.size:  # common is a subset of got: positions of its ids
            out[c] = np.searchsorted(got, common)
    return out


def warmup(backend: str = "auto", epipolar_gate: str = "mesh") -> None:
    """Compile (or load from numba's on-disk cache) the gates' numba kernels now, so a node's
    first frame does not pay for it. No-op for the numpy backend or without numba."""
    from maem_ros.core.association.gates import epipolar, reprojection, screening

    if reprojection_kernel(backend) is None:
        return
    if epipolar_gate != "none":
        epipolar.warmup()
        screening.warmup()
    reprojection.warmup(backend)
