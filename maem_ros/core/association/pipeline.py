"""MAEM stage 2: cross-view association of per-camera detections into people (clusters).

For every camera pair (a, b), a < b in rig order (doc/design.md §1):
1. tau_det: detections with score < tau_det take no part.
2. Reprojection gate: the two bbox centres are DLT-triangulated and reprojected into both
   views (rectified px); the pair is rejected if the error (mean of the two views, or max)
   is >= tau_reproj_bbox, or if the point lies behind either camera (it does not reproject
   into that view; epipolar geometry alone cannot see this).
3. Epipolar gate on the survivors: mean point-to-epipolar-line distance over all mesh
   vertices ("mesh") or 2D keypoints ("sparse"); rejected if >= tau_mesh (core/association/gates/epipolar.py).
4. Pair cost: PA-MPJPE (metres) between the two detections' 3D keypoints on ``cost_joints``
   (default the 13 body joints), plus ``cost_epipolar_weight`` x the pair's mean epipolar
   distance as a fraction of tau_mesh; pairs above ``tau_cost`` never match.
5. Clustering (core/association/clustering.py), ``clustering``:
   ``consistent`` (default): best-first merges over all camera pairs at once, each merge
   verified at cluster level (no two detections of one camera, most cross pairs gated,
   every member's reprojection error of the triangulated body joints under tau_verify),
   then local moves that raise the clustering objective;
   ``paper``: Hungarian per camera pair, union-find, same-camera conflict removal (MAEM);
   ``spectral``: the seed paper's PA-MPJPE matching baseline (no geometric gates).
   Clusters with fewer than k_min views are discarded.

All 2D input is rectified pinhole px (FrameDetections), so only Camera.P and F are used.
"""
from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field
from typing import Mapping, NamedTuple

import numpy as np

from maem_ros.core.association import clustering
from maem_ros.core.association import clustering_kernel
from maem_ros.core.association.gates import epipolar
from maem_ros.core.geometry import procrustes_kernel
from maem_ros.core.geometry.camera import Rig, fundamental_matrix
from maem_ros.core.detections import (PASSED, REJECTED_COST, REJECTED_EPIPOLAR, REJECTED_REPROJ, Cluster,
                         DetectionTable, FrameDetections, PairSet)
from maem_ros.core.geometry.multiview import pair_reprojection_bound, pair_reprojection_errors
from maem_ros.core.intsets import sorted_unique
from maem_ros.core.paramspec import Params, param
from maem_ros.core.geometry.procrustes import pa_mpjpe_pairs
from maem_ros.core.skeleton import joint_subset

#: overrides that give the MAEM paper's pipeline exactly: PA-MPJPE on every keypoint, no cost
#: cap, every pair's mesh distance over all vertices (no screen), per-pair Hungarian +
#: union-find + conflict removal
PAPER_PIPELINE = {"clustering": "paper", "cost_joints": "all", "tau_cost": 0.0,
                  "cost_epipolar_weight": 0.0, "screen_stride": 1, "screen_coarse_stride": 1}


@dataclass
class AssociationParams(Params):
    """Thresholds (px, m, score) and switches of MAEM stage 2; one field = one parameter of the
    association node (core/paramspec.py: add a field with ``param()`` and it is validated, read
    from params files and declared, with --help, by the node).

    ``backend`` selects the kernels of the gates (epipolar, reprojection), the pair cost and
    the clustering (auto = numba when installed, else numpy); both give the same decisions.
    ``epipolar_precision`` (numba): ``mixed`` float32 distances with a rigorous rounding-error
    bound (undecided pairs redone in float64; means ~1e-5 relative), ``float64`` (means
    ~1e-13). ``cost_joints``: "body" (the 13 sportcenter body joints of the detections'
    keypoint convention), "all", or comma-separated keypoint indices.
    ``tau_cost`` (m): pairs whose cost is above it never match; 0 = no cap (the paper).
    ``cost_epipolar_weight`` (m) adds the pair's mean epipolar distance, as a fraction of
    tau_mesh (so the term scales with the gate: mesh px, keypoint px), to its cost.
    ``tau_verify`` (px), ``min_support`` (fraction): the consistent clustering's merge checks.
    """

    tau_det: float = param(0.9, "detection score threshold", minimum=0.0, maximum=1.0)
    tau_reproj_bbox: float = param(10.0, "px, bbox-centre reprojection gate", minimum=0.0,
                                   exclusive_minimum=True)
    tau_mesh: float = param(8.0, "px, dense-mesh epipolar gate", minimum=0.0,
                            exclusive_minimum=True)
    k_min: int = param(4, "minimum views per cluster", minimum=2)
    reproj_gate: bool = param(True, "apply the bbox-centre reprojection gate")
    reproj_reduce: str = param("mean", "reprojection error of the pair", choices=("mean", "max"))
    epipolar_gate: str = param("mesh", "epipolar gate", choices=("mesh", "sparse", "none"))
    epipolar_distance: str = param("symmetric", "point-to-line distance direction",
                                   choices=("symmetric", "forward"))
    vertex_stride: int = param(1, "use every n-th mesh vertex", minimum=1)
    vertex_count: int = param(0, "use at most this many vertices (0 = all)", minimum=0)
    early_exit: bool = param(True, "stop the mesh distance early once a pair cannot pass")
    screen_stride: int = param(8, "mesh gate: decide pairs on 1/n of the gate vertices (runs "
                                  "of 8 consecutive ones) first, on the full set only within "
                                  "screen_margin of tau_mesh (1 = off: every pair on the full "
                                  "set, the paper)", minimum=1)
    screen_margin: float = param(1.0, "px, mesh gate: subset means within this of tau_mesh are "
                                      "decided on the full set", minimum=0.0)
    screen_coarse_stride: int = param(32, "mesh gate, before the screen: decide pairs on 1/n of "
                                          "the gate vertices (runs of 8), on the screen only "
                                          "within screen_coarse_margin of tau_mesh (1 = off; "
                                          "only with a screen, and coarser than it)", minimum=1)
    screen_coarse_margin: float = param(2.5, "px, mesh gate: coarse subset means within this of "
                                             "tau_mesh go on to the screen", minimum=0.0)
    backend: str = param("auto", "kernels of the gates (epipolar, reprojection), the pair cost "
                                 "and the clustering (auto = numba when installed, else numpy)",
                         choices=epipolar.BACKENDS)
    epipolar_precision: str = param("mixed", "numba kernel arithmetic: mixed (float32 SIMD with "
                                             "a rounding-error bound, float64 decisions) or "
                                             "float64", choices=epipolar.PRECISIONS)
    clustering: str = param("consistent", "consistent (verified best-first merges), paper "
                                          "(Hungarian + union-find) or spectral (PA-MPJPE "
                                          "matching baseline)", choices=clustering.METHODS)
    cost_joints: str = param("body", "pair-cost keypoints: body (13 body joints), all, or "
                                     "comma-separated indices")
    tau_cost: float = param(0.21, "m, pairs whose cost is above this never match (0 = no cap)",
                            minimum=0.0)
    cost_epipolar_weight: float = param(0.04, "m added to the pair cost per tau_mesh of mean "
                                               "epipolar distance", minimum=0.0)
    tau_verify: float = param(10.0, "px, consistent merges: each member's median reprojection "
                                    "error of the triangulated body joints", minimum=0.0,
                              exclusive_minimum=True)
    min_support: float = param(0.6, "consistent merges: fraction of cross pairs that passed "
                                    "the gates", minimum=0.0, maximum=1.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.clustering == "consistent" and self.tau_cost == 0:
            raise ValueError("tau_cost: the consistent clustering needs a cost cap > 0 m")
        joint_subset(self.cost_joints, None)
        if 1 < self.screen_coarse_stride <= self.screen_stride:
            raise ValueError(f"screen_coarse_stride: must be 1 (off) or coarser than "
                             f"screen_stride ({self.screen_stride}), got "
                             f"{self.screen_coarse_stride}")

    def screen_levels(self) -> list[tuple[int, float]]:
        """(stride, margin px) of the mesh gate's screening levels, coarse to fine (empty: every
        pair on the full set)."""
        if self.screen_stride <= 1:
            return []
        levels = [(self.screen_stride, self.screen_margin)]
        if self.screen_coarse_stride > 1:
            levels.insert(0, (self.screen_coarse_stride, self.screen_coarse_margin))
        return levels


@dataclass
class AssociationResult:
    """Clusters ordered by their first member (camera, detection); per-stage stats.

    ``table`` and ``pairs`` are the frame set's kept detections and every candidate pair with
    the stage that rejected it (for diagnosis: maem-eval --explain); ``groups`` the clusters
    before k_min as table rows, ``conflicts`` rows dropped by conflict removal (paper).
    """

    clusters: list[Cluster]
    stats: dict[str, float] = field(default_factory=dict)
    table: DetectionTable | None = None
    pairs: PairSet | None = None
    groups: list[np.ndarray] = field(default_factory=list)
    conflicts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


# ---------------------------------------------------------------------------------------
# rig geometry (P, F) cached per Rig object
# ---------------------------------------------------------------------------------------
class _RigGeometry(NamedTuple):
    """A rig's cached geometry (recomputed when a camera's intrinsics or pose change)."""

    key: tuple  # the cameras' names, K_rect, R, t as bytes
    P: np.ndarray  # (C,3,4) rectified world -> px
    F: dict[tuple[int, int], np.ndarray]  # F[(a, b)], a < b, x_b^T F x_a = 0
    stack: np.ndarray  # (C,C,3,3) F[a, b] both ways, zero diagonal
    pairs: epipolar.PairMatrices  # F as the epipolar kernels take it


_GEOMETRY: "weakref.WeakKeyDictionary[Rig, _RigGeometry]" = weakref.WeakKeyDictionary()


def rig_geometry(rig: Rig) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]]:
    """(P (C,3,4) rectified world->px, F[(a,b)] with x_b^T F x_a = 0) for the rig."""
    hit = _rig_cache(rig)
    return hit.P, hit.F


def _fundamental_stack(rig: Rig) -> np.ndarray:
    """(C,C,3,3) F[a, b] with x_b^T F[a, b] x_a = 0 for every camera pair (F[b, a] = F[a, b]^T,
    zero diagonal), for the reprojection gate's bound."""
    return _rig_cache(rig).stack


def _rig_cache(rig: Rig) -> _RigGeometry:
    key = tuple((c.name, c.K_rect.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in rig)
    hit = _GEOMETRY.get(rig)
    if hit is not None and hit.key == key:
        return hit
    cams = rig.cameras
    P = np.stack([c.P for c in cams])
    F = {(a, b): fundamental_matrix(cams[a], cams[b])
         for a in range(len(cams)) for b in range(a + 1, len(cams))}
    stack = np.zeros((len(cams), len(cams), 3, 3))
    for (a, b), f in F.items():
        stack[a, b], stack[b, a] = f, f.T
    _GEOMETRY[rig] = hit = _RigGeometry(key, P, F, stack, epipolar.pair_matrices(F))
    return hit


# ---------------------------------------------------------------------------------------
# input checks
# ---------------------------------------------------------------------------------------
def _check_frames(rig: Rig, frames: Mapping[str, FrameDetections],
                  params: AssociationParams) -> dict[int, FrameDetections]:
    """Frames by camera index; ValueError naming the camera/field on bad input."""
    by_index: dict[int, FrameDetections] = {}
    joints: set[int] = set()
    verts: set[int] = set()
    for name, fd in frames.items():
        if name not in rig:
            raise ValueError(f"frames: unknown camera {name!r}; rig cameras: {rig.names}")
        if not isinstance(fd, FrameDetections):
            raise ValueError(f"frames[{name!r}]: expected FrameDetections, got {type(fd).__name__}")
        if fd.camera != name:
            raise ValueError(f"frames[{name!r}]: camera: detections are of camera {fd.camera!r}")
        fd.validate()  # returns at once for frames the wire decoder validated
        if fd.n:
            joints.add(fd.num_joints)
            verts.add(fd.mesh_vertices)
        by_index[rig.index(name)] = fd
    if len(joints) > 1:
        raise ValueError(f"kpts2d: cameras disagree on the number of keypoints {sorted(joints)}")
    if params.epipolar_gate == "mesh" and by_index and verts:
        if len(verts) > 1:
            raise ValueError(f"verts2d: cameras disagree on the number of mesh vertices "
                             f"{sorted(verts)} (full mesh, before any announced subset)")
        if 0 in verts:
            raise ValueError("verts2d: epipolar_gate 'mesh' needs mesh vertices, got V=0 "
                             "(use epipolar_gate 'sparse' or 'none')")
    if joints:
        joint_subset(params.cost_joints, next(iter(joints)))
    return by_index


# ---------------------------------------------------------------------------------------
# candidate pairs and gates
# ---------------------------------------------------------------------------------------
def _enumerate_pairs(table: DetectionTable) -> tuple[np.ndarray, np.ndarray]:
    """Rows (i, j) of every kept x kept pair of every camera pair a < b, grouped by camera pair
    in order, each group row-major (i, then j)."""
    sizes = np.diff(table.offsets)
    a, b = np.triu_indices(sizes.size, 1)
    count = sizes[a] * sizes[b]
    some = count > 0
    a, b, count = a[some], b[some], count[some]
    group = np.repeat(np.arange(count.size), count)
    k = np.arange(int(count.sum())) - (np.cumsum(count) - count)[group]
    width = sizes[b][group]
    return table.offsets[a][group] + k // width, table.offsets[b][group] + k % width


def _reprojection_gate(table: DetectionTable, i: np.ndarray, j: np.ndarray, rig: Rig,
                       params: AssociationParams, geometry: _RigGeometry | None = None
                       ) -> np.ndarray:
    """(S,) pairs whose bbox-centre reprojection error is under tau_reproj_bbox.

    The epipolar lower bound of the error (geometry.pair_reprojection_bound) rejects most
    pairs of different people without triangulating; the rest get the DLT. The bound keeps a
    relative margin for rounding, so the decisions are exactly the DLT's.
    """
    geometry = _rig_cache(rig) if geometry is None else geometry
    P, stack = geometry.P, geometry.stack
    bound = pair_reprojection_bound(stack, table.cam, table.centers, i, j, params.reproj_reduce)
    ok = np.zeros(i.size, bool)
    todo = np.flatnonzero(~(bound > params.tau_reproj_bbox * (1.0 + _BOUND_MARGIN)))
    if todo.size:
        errors = pair_reprojection_errors(P[table.cam], table.centers, i[todo], j[todo],
                                          params.reproj_reduce)
        ok[todo] = errors < params.tau_reproj_bbox
    return ok


#: relative margin of the reprojection bound over tau_reproj_bbox before it rejects alone
#: (its own rounding is ~1e-13 relative)
_BOUND_MARGIN = 1e-6


def warmup(backend: str = "auto", epipolar_gate: str = "mesh") -> None:
    """Compile (or load from numba's on-disk cache) the gates' numba kernels now, so a node's
    first frame does not pay for it. No-op for the numpy backend or without numba."""
    kernel = _reprojection_kernel(backend)
    if kernel is None:
        return
    if epipolar_gate != "none":
        epipolar.warmup()
    procrustes_kernel.warmup()
    clustering_kernel.warmup()
    P = np.zeros((2, 3, 4))
    kernel(np.arange(3, dtype=np.int64), np.zeros((2, 2, 3, 3)), P, np.zeros((2, 2)), 1.0,
           _BOUND_MARGIN, False)


def _reprojection_kernel(backend: str):
    """The numba pass of enumeration + reprojection gate (core/association/gates/reprojection_kernel.py; same
    pairs, order and decisions as _enumerate_pairs + _reprojection_gate), or None for the
    numpy path (``backend`` numpy, or numba not installed)."""
    if backend == "numpy" or not epipolar.have_numba():
        return None
    from maem_ros.core.association.gates.reprojection_kernel import reprojection_gate
    return reprojection_gate


def _gate_points(frames: dict[int, FrameDetections], params: AssociationParams
                 ) -> dict[int, tuple[epipolar.PointRows, list[epipolar.PointRows | None]]]:
    """Per camera, the points the epipolar gate compares (vertices or keypoints) and their
    screening subsets (mesh gate, :meth:`AssociationParams.screen_levels`, coarse to fine;
    None = too few points), in the layout the kernel reads: built once per camera (not per
    camera pair), the full set a view of the decoded message when the gate uses every vertex
    it received."""
    if params.epipolar_gate == "sparse":
        return {c: (epipolar.point_rows(fd.kpts2d), []) for c, fd in frames.items()}
    columns = _gate_columns(frames, params)
    out = {}
    for c, fd in frames.items():
        whole = columns[c] is None
        full = (epipolar.point_rows(fd.verts2d, fd.block_ranges()) if whole
                else epipolar.point_rows(fd.verts2d[:, columns[c]]))
        out[c] = (full, screen_subsets(full, params, fd if whole else None))
    return out


def decode_screen_strides(params: AssociationParams) -> tuple[int, ...]:
    """The screening strides whose subsets a decoder should copy for the mesh gate
    (FrameDetections.attach_screens, epipolar.screen_copies): those of the screening levels
    when the numba gate compares every vertex a camera sends, else none (the gate would not
    read them; the numpy backend reads the subsets in place)."""
    if params.epipolar_gate != "mesh" or params.vertex_stride != 1 or params.vertex_count > 0 \
            or params.backend == "numpy" or not epipolar.have_numba():
        return ()
    return tuple(stride for stride, _ in params.screen_levels())


def screen_subsets(x: np.ndarray | epipolar.PointRows, params: AssociationParams,
                   fd: FrameDetections | None = None) -> list[epipolar.PointRows | None]:
    """One camera's (N,n,2) gate points (or their full-set PointRows) -> the subset of each
    screening level (coarse to fine, :meth:`AssociationParams.screen_levels`; None where too
    few points to screen with): the decoder's contiguous copy (FrameDetections.screen_copy)
    when ``fd`` is given (x is its whole verts2d) and has one, else read in place."""
    out = []
    for stride, _ in params.screen_levels():
        copy = fd.screen_copy(stride) if fd is not None else None
        out.append(epipolar.screen_rows(x, stride) if copy is None
                   else epipolar.point_rows(copy, fd.block_ranges(stride)))
    return out


def screen_levels(points: Mapping[int, tuple[epipolar.PointRows, list[epipolar.PointRows | None]]],
                  params: AssociationParams) -> list[epipolar.ScreenLevel]:
    """The screening levels of epipolar.frame_screened_means from per-camera (full, subsets):
    the levels every camera has a subset for (keypoints have none), with their margins."""
    levels = []
    for k, (_, margin) in enumerate(params.screen_levels()):
        subsets = {c: rows[k] if k < len(rows) else None for c, (_, rows) in points.items()}
        if all(v is not None for v in subsets.values()):
            levels.append((subsets, margin))
    return levels


def _gate_columns(frames: dict[int, FrameDetections], params: AssociationParams
                  ) -> dict[int, np.ndarray | None]:
    """Per camera, the verts2d columns the mesh gate uses (None = all of them, no copy).

    The gate compares full-mesh vertex ids: the ones the params select (vertex_stride /
    vertex_count on the full mesh) that every camera with detections sent (a frontend may send
    an announced subset, FrameDetections.vertex_ids).
    """
    live = {c: fd for c, fd in frames.items() if fd.n}
    if not live:
        return {c: None for c in frames}
    mesh = next(iter(live.values())).mesh_vertices
    wanted = epipolar.vertex_subset(mesh, params.vertex_stride, params.vertex_count)
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


def _epipolar_gate(table: DetectionTable, i: np.ndarray, j: np.ndarray,
                   F: epipolar.PairMatrices, params: AssociationParams,
                   stats: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """(keep (S,) bool, mean distance (S,) px, exact where kept) of pairs (i, j)."""
    points = _gate_points(table.frames, params)
    full = {c: rows for c, (rows, _) in points.items()}
    # one kernel call for every camera pair of the frame (per level): a detection's block is
    # read once from memory for all its candidate pairs
    keep, mean, evaluated = epipolar.frame_screened_means(
        full, screen_levels(points, params), F, table.cam[i], table.det[i], table.cam[j],
        table.det[j], params.tau_mesh, symmetric=params.epipolar_distance == "symmetric",
        early_exit=params.early_exit, backend=params.backend,
        precision=params.epipolar_precision)
    budget = i.size * next(iter(full.values())).n if full else 0
    stats["epipolar_points_fraction"] = evaluated / budget if budget else 0.0
    return keep, mean


class PoseCosts:
    """Pair costs (m) of one frame set: PA-MPJPE on ``joints`` of table row a aligned onto row
    b, each pair computed once (the gates', the clustering's and the clusters' costs share it).

    The rows' 3D keypoints are laid out once coordinate-first (3,J,N), the layout the batched
    closed-form Procrustes (core/geometry/procrustes.py) computes on.
    """

    def __init__(self, table: DetectionTable, joints: np.ndarray, backend: str = "auto"):
        self.columns = np.ascontiguousarray(table.kpts3d[:, joints].transpose(2, 1, 0))
        self.known = np.full((len(table), len(table)), np.nan)
        self.backend = backend
        self._none_known = True

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(S,) costs of rows a onto rows b."""
        if self._none_known:  # the first call (the gates'): no lookup
            self._none_known = False
            out = pa_mpjpe_pairs(self.columns, a, b, self.backend)
            self.known[a, b] = out
            return out
        out = self.known[a, b]
        todo = np.flatnonzero(np.isnan(out))
        if todo.size:
            out[todo] = pa_mpjpe_pairs(self.columns, a[todo], b[todo], self.backend)
            self.known[a[todo], b[todo]] = out[todo]
        return out


def gate_pairs(rig: Rig, table: DetectionTable, params: AssociationParams,
               stats: dict[str, float], costs: PoseCosts | None = None) -> PairSet:
    """Steps 2-4 of the method on every kept pair: gates, costs (computed by ``costs``, by
    default a new PoseCosts of the table), the cost cap."""
    geometry = _rig_cache(rig)
    t = time.perf_counter()
    kernel = _reprojection_kernel(params.backend) if params.reproj_gate else None
    if kernel is not None:  # enumeration and gate in one pass
        i, j, ok = kernel(table.offsets, geometry.stack, geometry.P[table.cam], table.centers,
                          float(params.tau_reproj_bbox), _BOUND_MARGIN,
                          params.reproj_reduce == "max")
    else:
        i, j = _enumerate_pairs(table)
        ok = (_reprojection_gate(table, i, j, rig, params, geometry)
              if params.reproj_gate and i.size else None)
    S = i.size
    if ok is not None:  # masks, not index arrays, over every pair (72,000 on the large load)
        stage = np.where(ok, np.int8(PASSED), np.int8(REJECTED_REPROJ))
        alive = np.flatnonzero(ok)
    else:
        stage = np.full(S, PASSED, np.int8)
        alive = np.arange(S)
    stats["rejected_reproj"] = float(S - alive.size)
    stats["t_reproj_ms"], t = _lap(t)

    epi = np.full(S, np.nan)
    stats["epipolar_points_fraction"] = 0.0
    if params.epipolar_gate != "none" and alive.size:
        ok, mean = _epipolar_gate(table, i[alive], j[alive], geometry.pairs, params, stats)
        epi[alive] = mean
        stage[alive[~ok]] = REJECTED_EPIPOLAR
        stats["rejected_epipolar"] = float(np.count_nonzero(~ok))
        alive = alive[ok]
    stats["t_epipolar_ms"], t = _lap(t)

    pose = np.full(S, np.nan)
    if alive.size:
        if costs is None:
            costs = PoseCosts(table, joint_subset(params.cost_joints, table.num_joints),
                              params.backend)
        pose[alive] = costs(i[alive], j[alive])
    # relative to the gate threshold, so one default fits dense-mesh px and keypoint px
    weight = (params.cost_epipolar_weight / params.tau_mesh if params.epipolar_gate != "none"
              else 0.0)
    cost = np.full(S, np.nan)  # NaN where a gate rejected the pair, as its pose cost
    cost[alive] = pose[alive] + weight * np.nan_to_num(epi[alive], nan=0.0)
    capped = ~np.isfinite(cost[alive])
    if params.tau_cost > 0:
        capped |= cost[alive] > params.tau_cost
    stage[alive[capped]] = REJECTED_COST
    stats["rejected_cost"] = float(np.count_nonzero(capped))
    stats["t_cost_ms"], _ = _lap(t)
    return PairSet(i=i, j=j, stage=stage, pose=pose, epi=epi, cost=cost)


# ---------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------
STAT_KEYS = ("pairs_considered", "rejected_score", "rejected_reproj", "rejected_epipolar",
             "rejected_cost", "matched_pairs", "merges", "merges_rejected", "moves", "conflicts_removed",
             "clusters_below_k_min", "t_reproj_ms", "t_epipolar_ms", "t_cost_ms",
             "t_match_ms", "t_cluster_ms", "t_total_ms")


def associate(rig: Rig, frames: Mapping[str, FrameDetections],
              params: AssociationParams) -> AssociationResult:
    """MAEM stage 2 on one synchronised frame set (frames keyed by camera name; absent = missing).

    Returns clusters (members index the detections as given) and per-stage stats: pair counts
    (considered, rejected by score / reprojection / epipolar gate / cost cap, matched), merges
    refused by verification, conflicts removed, clusters below k_min, and the time of each
    stage in ms.
    """
    t_start = time.perf_counter()
    stats: dict[str, float] = dict.fromkeys(STAT_KEYS, 0.0)
    by_index = _check_frames(rig, frames, params)
    kept = {c: np.flatnonzero(fd.scores >= params.tau_det) for c, fd in by_index.items()}
    table = DetectionTable.build(by_index, len(rig), kept)
    n_all = np.array([by_index[c].n for c in sorted(by_index)])
    n_kept = np.array([kept[c].size for c in sorted(by_index)])
    stats["detections"] = float(n_all.sum())
    stats["detections_kept"] = float(n_kept.sum())
    stats["pairs_considered"] = float((n_all.sum() ** 2 - (n_all ** 2).sum()) / 2)
    stats["rejected_score"] = stats["pairs_considered"] - float(
        (n_kept.sum() ** 2 - (n_kept ** 2).sum()) / 2)
    joints = joint_subset(params.cost_joints, table.num_joints) if len(table) else None
    pair_cost = PoseCosts(table, joints, params.backend) if len(table) else None
    pairs = gate_pairs(rig, table, params, stats, pair_cost)

    t = time.perf_counter()
    P, _ = rig_geometry(rig)
    found = clustering.cluster(table, pairs, P, joints, params, stats, pair_cost)
    stats["t_cluster_ms"], _ = _lap(t)

    kept_groups = _views_at_least(table, found, params.k_min)
    stats["clusters_below_k_min"] += float(len(found.groups) - len(kept_groups))
    clusters = [Cluster(members=table.members(g), costs=c)
                for g, c in zip(kept_groups, clustering.mean_costs(kept_groups, pair_cost))]
    clusters.sort(key=lambda c: tuple(c.members[0].tolist()))
    stats["clusters"] = float(len(clusters))
    stats["t_total_ms"] = (time.perf_counter() - t_start) * 1e3
    return AssociationResult(clusters=clusters, stats=stats, table=table, pairs=pairs,
                             groups=found.groups, conflicts=found.conflicts)


def _views_at_least(table: DetectionTable, found: clustering.Found, k_min: int
                    ) -> list[np.ndarray]:
    """The groups (table rows, conflicts removed, in order) seen by at least k_min cameras."""
    if not found.groups:
        return []
    rows = np.concatenate(found.groups)
    group = np.repeat(np.arange(len(found.groups)), [g.size for g in found.groups])
    alive = np.ones(len(table), bool)
    alive[found.conflicts] = False
    rows, group = rows[alive[rows]], group[alive[rows]]
    C = int(table.cam.max()) + 1
    views = np.bincount(sorted_unique(group * C + table.cam[rows]) // C,
                        minlength=len(found.groups))
    keep = np.flatnonzero(views >= k_min)
    bounds = zip(group.searchsorted(keep, "left").tolist(), group.searchsorted(keep, "right").tolist())
    return [rows[start:end] for start, end in bounds]


def _lap(t: float) -> tuple[float, float]:
    now = time.perf_counter()
    return (now - t) * 1e3, now
