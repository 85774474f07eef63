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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

import maem_ros.core.association.clustering as clustering
import maem_ros.core.association.clustering_kernel as clustering_kernel
import maem_ros.core.geometry.procrustes_kernel as procrustes_kernel
from maem_ros.core.association.clustering_groups import mean_to_rest
from maem_ros.core.association.gates import PairGates
from maem_ros.core.association.gates import warmup as warmup_gates
from maem_ros.core.association.params import PAPER_PIPELINE, AssociationParams
from maem_ros.core.detections import (
    PASSED,
    REJECTED_COST,
    REJECTED_EPIPOLAR,
    Cluster,
    DetectionTable,
    FrameDetections,
    PairSet,
)
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.geometry.procrustes import pa_mpjpe_pairs
from maem_ros.core.intsets import sorted_unique
from maem_ros.core.skeleton import joint_subset

__all__ = [
    "PAPER_PIPELINE",
    "STAT_KEYS",
    "AssociationParams",
    "AssociationResult",
    "PoseCosts",
    "associate",
    "gate_pairs",
    "warmup",
]


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
# input checks
# ---------------------------------------------------------------------------------------
def _check_frames(
    rig: Rig, frames: Mapping[str, FrameDetections], params: AssociationParams
) -> dict[int, FrameDetections]:
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
            raise ValueError(
                f"verts2d: cameras disagree on the number of mesh vertices "
                f"{sorted(verts)} (full mesh, before any announced subset)"
            )
        if 0 in verts:
            raise ValueError(
                "verts2d: epipolar_gate 'mesh' needs mesh vertices, got V=0 "
                "(use epipolar_gate 'sparse' or 'none')"
            )
    if joints:
        joint_subset(params.cost_joints, next(iter(joints)))
    return by_index


# ---------------------------------------------------------------------------------------
# gates and costs
# ---------------------------------------------------------------------------------------
def warmup(backend: str = "auto", epipolar_gate: str = "mesh") -> None:
    """Compile (or load from numba's on-disk cache) the numba kernels of the gates, the pair
    cost and the clustering now, so a node's first frame does not pay for it. No-op for the
    numpy backend or without numba."""
    if backend == "numpy" or not clustering_kernel.have_numba():
        return
    warmup_gates(backend, epipolar_gate)
    procrustes_kernel.warmup()
    clustering_kernel.warmup()


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


def pair_cost(pose: np.ndarray, epi: np.ndarray, params: AssociationParams, epipolar_gate: str) -> np.ndarray:
    """(S,) m: the cost of pairs that passed the gates, their pose cost pose (S,) m plus
    ``cost_epipolar_weight`` per ``tau_mesh`` of their mean epipolar distance epi (S,) px
    (NaN = not measured: 0) under ``epipolar_gate`` (relative to the gate threshold, so one
    default fits dense-mesh px and keypoint px; no term without an epipolar gate)."""
    weight = params.cost_epipolar_weight / params.tau_mesh if epipolar_gate != "none" else 0.0
    return pose + weight * np.nan_to_num(epi, nan=0.0)


def gate_pairs(
    rig: Rig,
    table: DetectionTable,
    params: AssociationParams,
    stats: dict[str, float],
    costs: PoseCosts | None = None,
    gates: PairGates | None = None,
) -> PairSet:
    """Steps 2-4 of the method on every kept pair: the pair gates (``gates``, by default new
    PairGates of the rig and params), costs (computed by ``costs``, by default a new PoseCosts
    of the table), the cost cap."""
    gates = PairGates(rig, params) if gates is None else gates
    t = time.perf_counter()
    i, j, ok = gates.candidates(table)  # with numba: enumeration and gate in one pass
    S = i.size
    stats["rejected_reproj"] = float(S - np.count_nonzero(ok)) if ok is not None else 0.0
    stats["t_reproj_ms"], t = _lap(t)
    decided = gates.frame_set(table.frames).decide_rows(table, i, j, ok)
    stage, epi = decided.stage, decided.epi
    stats["epipolar_points_fraction"] = decided.points_fraction
    alive = np.flatnonzero(stage == PASSED)
    stats["rejected_epipolar"] = float(np.count_nonzero(stage == REJECTED_EPIPOLAR))
    stats["t_epipolar_ms"], t = _lap(t)

    pose = np.full(S, np.nan)
    if alive.size:
        if costs is None:
            costs = PoseCosts(
                table, joint_subset(params.cost_joints, table.num_joints), params.execution.backend
            )
        pose[alive] = costs(i[alive], j[alive])
    cost = np.full(S, np.nan)  # NaN where a gate rejected the pair, as its pose cost
    cost[alive] = pair_cost(pose[alive], epi[alive], params, params.epipolar_gate)
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
STAT_KEYS = (
    "pairs_considered",
    "rejected_score",
    "rejected_reproj",
    "rejected_epipolar",
    "rejected_cost",
    "matched_pairs",
    "merges",
    "merges_rejected",
    "moves",
    "conflicts_removed",
    "clusters_below_k_min",
    "t_reproj_ms",
    "t_epipolar_ms",
    "t_cost_ms",
    "t_match_ms",
    "t_cluster_ms",
    "t_total_ms",
)


def associate(
    rig: Rig, frames: Mapping[str, FrameDetections], params: AssociationParams, gates: PairGates | None = None
) -> AssociationResult:
    """MAEM stage 2 on one synchronised frame set (frames keyed by camera name; absent = missing).

    Returns clusters (members index the detections as given) and per-stage stats: pair counts
    (considered, rejected by score / reprojection / epipolar gate / cost cap, matched), merges
    refused by verification, conflicts removed, clusters below k_min, and the time of each
    stage in ms. ``gates``: the PairGates (of this rig and params) that prepared the frames
    as they arrived, if any (PairGates.prepare); by default new ones.
    """
    t_start = time.perf_counter()
    stats: dict[str, float] = dict.fromkeys(STAT_KEYS, 0.0)
    by_index = _check_frames(rig, frames, params)
    kept = {c: np.flatnonzero(fd.scores >= params.tau_det) for c, fd in by_index.items()}
    table = DetectionTable.build(by_index, len(rig), kept)
    stats.update(
        score_counts([by_index[c].n for c in sorted(by_index)], [kept[c].size for c in sorted(by_index)])
    )
    joints = joint_subset(params.cost_joints, table.num_joints) if len(table) else None
    pair_cost = PoseCosts(table, joints, params.execution.backend) if joints is not None else None
    gates = PairGates(rig, params) if gates is None else gates
    pairs = gate_pairs(rig, table, params, stats, pair_cost, gates)

    t = time.perf_counter()
    # no joints nor pair cost only for an empty table, which has nothing to cluster
    found = (
        clustering.cluster(table, pairs, gates.geometry.P, joints, params, stats, pair_cost)
        if joints is not None and pair_cost is not None
        else clustering.Found([])
    )
    stats["t_cluster_ms"], _ = _lap(t)

    kept_groups = _views_at_least(table, found, params.k_min)
    stats["clusters_below_k_min"] += float(len(found.groups) - len(kept_groups))
    costs = mean_costs(kept_groups, pair_cost) if pair_cost is not None else []
    clusters = [Cluster(members=table.members(g), costs=c) for g, c in zip(kept_groups, costs)]
    clusters.sort(key=lambda c: tuple(c.members[0].tolist()))
    stats["clusters"] = float(len(clusters))
    stats["t_total_ms"] = (time.perf_counter() - t_start) * 1e3
    return AssociationResult(
        clusters=clusters,
        stats=stats,
        table=table,
        pairs=pairs,
        groups=found.groups,
        conflicts=found.conflicts,
    )


def score_counts(detections: Sequence[int], kept: Sequence[int]) -> dict[str, float]:
    """The stats of stage 1 from per-camera counts of detections and of those kept (score >=
    tau_det): detections, detections_kept, pairs_considered (every pair of detections of two
    cameras) and rejected_score (those with a detection below tau_det)."""
    n_all, n_kept = np.asarray(detections, np.int64), np.asarray(kept, np.int64)
    considered = float((n_all.sum() ** 2 - (n_all**2).sum()) / 2)
    return {
        "detections": float(n_all.sum()),
        "detections_kept": float(n_kept.sum()),
        "pairs_considered": considered,
        "rejected_score": considered - float((n_kept.sum() ** 2 - (n_kept**2).sum()) / 2),
    }


def mean_costs(groups: list[np.ndarray], pair_cost: PoseCosts) -> list[np.ndarray]:
    """Per group (table rows), each member's mean pose cost (m) to the rest (member m aligned
    onto n for m < n; NaN if alone), all groups' pairs in one batch, groups of one size
    reduced together."""
    out: list[np.ndarray] = [np.zeros(0)] * len(groups)
    sizes = np.array([g.size for g in groups], np.int64)
    batches = [(m, np.flatnonzero(sizes == m)) for m in np.unique(sizes).tolist()]
    r, c, a_parts, b_parts = {}, {}, [], []
    for m, which in batches:
        r[m], c[m] = np.triu_indices(m, 1)
        rows = np.stack([groups[k] for k in which.tolist()])  # (G,m)
        a_parts.append(rows[:, r[m]].ravel())
        b_parts.append(rows[:, c[m]].ravel())
    a = np.concatenate(a_parts + [np.zeros(0, np.int64)])
    b = np.concatenate(b_parts + [np.zeros(0, np.int64)])
    flat = pair_cost(a, b) if a.size else np.zeros(0)
    k = 0
    for m, which in batches:
        Cm = np.full((which.size, m, m), np.nan)
        n = which.size * r[m].size
        Cm[:, r[m], c[m]] = Cm[:, c[m], r[m]] = flat[k : k + n].reshape(which.size, -1)
        k += n
        for g, mean in zip(which.tolist(), mean_to_rest(Cm, np.ones(m, bool))):
            out[g] = mean
    return out


def _views_at_least(table: DetectionTable, found: clustering.Found, k_min: int) -> list[np.ndarray]:
    """The groups (table rows, conflicts removed, in order) seen by at least k_min cameras."""
    if not found.groups:
        return []
    rows = np.concatenate(found.groups)
    group = np.repeat(np.arange(len(found.groups)), [g.size for g in found.groups])
    alive = np.ones(len(table), bool)
    alive[found.conflicts] = False
    rows, group = rows[alive[rows]], group[alive[rows]]
    C = int(table.cam.max()) + 1
    views = np.bincount(sorted_unique(group * C + table.cam[rows]) // C, minlength=len(found.groups))
    keep = np.flatnonzero(views >= k_min)
    bounds = zip(group.searchsorted(keep, "left").tolist(), group.searchsorted(keep, "right").tolist())
    return [rows[start:end] for start, end in bounds]


def _lap(t: float) -> tuple[float, float]:
    now = time.perf_counter()
    return (now - t) * 1e3, now
