"""MAEM stage 2: cross-view association of per-camera detections into people (clusters).

For every camera pair (a, b), a < b in rig order (DESIGN.md §1):
1. tau_det: detections with score < tau_det take no part.
2. Reprojection gate: the two bbox centres are DLT-triangulated and reprojected into both
   views (rectified px); the pair is rejected if the error (mean of the two views, or max)
   is >= tau_reproj_bbox, or if the point lies behind either camera (it does not reproject
   into that view; epipolar geometry alone cannot see this).
3. Epipolar gate on the survivors: mean point-to-epipolar-line distance over all mesh
   vertices ("mesh") or 2D keypoints ("sparse"); rejected if >= tau_mesh (core/epipolar.py).
4. Cost = PA-MPJPE (metres) between the two detections' 3D keypoints (the lower camera's
   aligned onto the other's); Hungarian per camera pair; gated pairs never match.
5. Union-find over all matches -> clusters; while a cluster holds two detections of one
   camera, the member with the highest mean PA-MPJPE to the rest is dropped; clusters with
   fewer than k_min views are discarded.

All 2D input is rectified pinhole px (FrameDetections), so only Camera.P and F are used.
"""
from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment

from . import epipolar
from .camera import Rig, fundamental_matrix
from .detections import FrameDetections
from .triangulation import dlt

_CHOICES = {
    "reproj_reduce": ("mean", "max"),
    "epipolar_gate": ("mesh", "sparse", "none"),
    "epipolar_distance": ("symmetric", "forward"),
    "backend": epipolar.BACKENDS,
}
#: cost given to gated pairs in the Hungarian matrix: any real match is preferred, and
#: an assignment that lands on it is discarded
_GATED = 1e9


@dataclass
class AssociationParams:
    """Thresholds (px, score) and ablation switches of MAEM stage 2.

    ``backend`` selects the epipolar kernel (auto = numba when installed, else numpy); both
    give the same decisions.
    """

    tau_det: float = 0.9
    tau_reproj_bbox: float = 10.0
    tau_mesh: float = 8.0
    k_min: int = 4
    reproj_gate: bool = True
    reproj_reduce: str = "mean"
    epipolar_gate: str = "mesh"
    epipolar_distance: str = "symmetric"
    vertex_stride: int = 1
    vertex_count: int = 0
    early_exit: bool = True
    backend: str = "auto"

    def __post_init__(self) -> None:
        for name in ("tau_det", "tau_reproj_bbox", "tau_mesh"):
            setattr(self, name, _number(name, getattr(self, name)))
        if not 0.0 <= self.tau_det <= 1.0:
            raise ValueError(f"tau_det: must be in [0, 1], got {self.tau_det}")
        for name in ("tau_reproj_bbox", "tau_mesh"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0 px, got {getattr(self, name)}")
        self.k_min = _integer("k_min", self.k_min, 2)
        self.vertex_stride = _integer("vertex_stride", self.vertex_stride, 1)
        self.vertex_count = _integer("vertex_count", self.vertex_count, 0)
        for name in ("reproj_gate", "early_exit"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name}: expected true/false, got {getattr(self, name)!r}")
            setattr(self, name, bool(getattr(self, name)))
        for name, choices in _CHOICES.items():
            if getattr(self, name) not in choices:
                raise ValueError(f"{name}: expected one of {list(choices)}, got "
                                 f"{getattr(self, name)!r}")

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> "AssociationParams":
        """Take the known keys of a params dict (others, e.g. slop, are ignored); validate."""
        return cls(**{f.name: d[f.name] for f in fields(cls) if f.name in d})


def _number(name: str, v: Any) -> float:
    if isinstance(v, (bool, str, np.bool_)) or not isinstance(v, (int, float, np.number)):
        raise ValueError(f"{name}: expected a number, got {v!r}")
    if not np.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {v}")
    return float(v)


def _integer(name: str, v: Any, minimum: int) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)) \
            or not np.isfinite(v) or int(v) != v:
        raise ValueError(f"{name}: expected an integer, got {v!r}")
    if int(v) < minimum:
        raise ValueError(f"{name}: must be >= {minimum}, got {int(v)}")
    return int(v)


@dataclass
class Cluster:
    """One person: members (M,2) int64 (camera index in rig order, detection index in that
    camera's FrameDetections as given), sorted; costs (M,) mean PA-MPJPE (m) of each member to
    the rest (each pair aligned lower member onto higher), NaN if alone.
    """

    members: np.ndarray
    costs: np.ndarray

    def __post_init__(self) -> None:
        self.members = np.asarray(self.members, dtype=np.int64).reshape(-1, 2)
        self.costs = np.asarray(self.costs, dtype=np.float64).reshape(-1)

    def __len__(self) -> int:
        return int(self.members.shape[0])


@dataclass
class AssociationResult:
    """Clusters ordered by their first member (camera, detection); per-stage stats."""

    clusters: list[Cluster]
    stats: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------
# rig geometry (P, F) cached per Rig object
# ---------------------------------------------------------------------------------------
_GEOMETRY: "weakref.WeakKeyDictionary[Rig, tuple]" = weakref.WeakKeyDictionary()


def _geometry(rig: Rig) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]]:
    """(P (C,3,4) rectified world->px, F[(a,b)] with x_b^T F x_a = 0) for the rig."""
    key = tuple((c.name, c.K_rect.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in rig)
    hit = _GEOMETRY.get(rig)
    if hit is not None and hit[0] == key:
        return hit[1], hit[2]
    cams = rig.cameras
    P = np.stack([c.P for c in cams])
    F = {(a, b): fundamental_matrix(cams[a], cams[b])
         for a in range(len(cams)) for b in range(a + 1, len(cams))}
    _GEOMETRY[rig] = (key, P, F)
    return P, F


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
        fd.validate()
        if fd.n:
            joints.add(fd.num_joints)
            verts.add(fd.num_vertices)
        by_index[rig.index(name)] = fd
    if len(joints) > 1:
        raise ValueError(f"kpts2d: cameras disagree on the number of keypoints {sorted(joints)}")
    if params.epipolar_gate == "mesh" and by_index and verts:
        if len(verts) > 1:
            raise ValueError(f"verts2d: cameras disagree on the number of mesh vertices "
                             f"{sorted(verts)}")
        if 0 in verts:
            raise ValueError("verts2d: epipolar_gate 'mesh' needs mesh vertices, got V=0 "
                             "(use epipolar_gate 'sparse' or 'none')")
    return by_index


# ---------------------------------------------------------------------------------------
# stages
# ---------------------------------------------------------------------------------------
@dataclass
class _Candidates:
    """Detection pairs still alive, flat over all camera pairs (a < b): camera indices ca, cb;
    original detection indices di, dj; positions pi, pj among the camera's kept detections."""

    ca: np.ndarray
    cb: np.ndarray
    di: np.ndarray
    dj: np.ndarray
    pi: np.ndarray
    pj: np.ndarray

    def select(self, keep: np.ndarray) -> "_Candidates":
        return _Candidates(*(getattr(self, f.name)[keep] for f in fields(self)))

    def __len__(self) -> int:
        return int(self.ca.size)


def _enumerate_pairs(frames: dict[int, FrameDetections], kept: dict[int, np.ndarray],
                     stats: dict[str, float]) -> _Candidates:
    """Every kept x kept detection pair of every camera pair a < b; counts score rejections."""
    cols: list[list[np.ndarray]] = [[] for _ in range(6)]
    cams = sorted(frames)
    for k, a in enumerate(cams):
        for b in cams[k + 1:]:
            total = frames[a].n * frames[b].n
            na, nb = kept[a].size, kept[b].size
            stats["pairs_considered"] += total
            stats["rejected_score"] += total - na * nb
            if na == 0 or nb == 0:
                continue
            pi, pj = np.repeat(np.arange(na), nb), np.tile(np.arange(nb), na)
            for col, v in zip(cols, (np.full(na * nb, a), np.full(na * nb, b), kept[a][pi],
                                     kept[b][pj], pi, pj)):
                col.append(v)
    if not cols[0]:
        return _Candidates(*(np.zeros(0, dtype=np.int64) for _ in range(6)))
    return _Candidates(*(np.concatenate(c).astype(np.int64) for c in cols))


def reprojection_errors(P: np.ndarray, uv: np.ndarray, reduce: str = "mean") -> np.ndarray:
    """(S,) px bbox-centre reprojection error of S two-view pairs.

    P (S,2,3,4) world -> rectified px; uv (S,2,2) the two centres. The centres are
    DLT-triangulated (core.triangulation.dlt) and reprojected into both views; the two errors
    are reduced by ``mean`` or ``max``. Inf when the point is behind either camera or the
    rays are degenerate.
    """
    X = dlt(P, uv)  # (S,3)
    h = np.einsum("svij,sj->svi", P[..., :3], X) + P[..., 3]  # (S,2,3)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(h[..., :2] / h[..., 2:3] - uv, axis=-1)
    err = np.where((h[..., 2] > 0) & np.isfinite(err), err, np.inf)
    return err.mean(axis=1) if reduce == "mean" else err.max(axis=1)


def _reprojection_gate(cand: _Candidates, frames: dict[int, FrameDetections], P: np.ndarray,
                       params: AssociationParams) -> np.ndarray:
    centres = {c: fd.centers for c, fd in frames.items()}
    uv = np.empty((len(cand), 2, 2))
    for c, cen in centres.items():
        sel = cand.ca == c
        uv[sel, 0] = cen[cand.di[sel]]
        sel = cand.cb == c
        uv[sel, 1] = cen[cand.dj[sel]]
    Ps = np.stack([P[cand.ca], P[cand.cb]], axis=1)
    return reprojection_errors(Ps, uv, params.reproj_reduce) < params.tau_reproj_bbox


def _gate_points(frames: dict[int, FrameDetections], params: AssociationParams
                 ) -> dict[int, np.ndarray]:
    """Per camera, the (N,n,2) rectified px the epipolar gate compares (vertices or keypoints)."""
    if params.epipolar_gate == "sparse":
        return {c: fd.kpts2d for c, fd in frames.items()}
    out = {}
    for c, fd in frames.items():
        subset = epipolar.vertex_subset(fd.num_vertices, params.vertex_stride,
                                        params.vertex_count) if fd.n else None
        out[c] = fd.verts2d if subset is None else fd.verts2d[:, subset]
    return out


def _epipolar_gate(cand: _Candidates, frames: dict[int, FrameDetections],
                   F: dict[tuple[int, int], np.ndarray], params: AssociationParams,
                   stats: dict[str, float]) -> np.ndarray:
    points = _gate_points(frames, params)
    keep = np.zeros(len(cand), dtype=bool)
    budget = evaluated = 0
    for a, b, idx in _groups(cand):
        xa, xb = points[a], points[b]
        sums, used = epipolar.epipolar_sums(
            xa, xb, F[(a, b)], cand.di[idx], cand.dj[idx], params.tau_mesh,
            symmetric=params.epipolar_distance == "symmetric", early_exit=params.early_exit,
            backend=params.backend)
        keep[idx] = sums < params.tau_mesh * xa.shape[1]
        budget += idx.size * xa.shape[1]
        evaluated += int(used.sum())
    stats["epipolar_points_fraction"] = evaluated / budget if budget else 0.0
    return keep


def _groups(cand: _Candidates):
    """(a, b, indices into cand) per camera pair, in order."""
    if len(cand) == 0:
        return
    key = cand.ca * 65536 + cand.cb
    bounds = np.flatnonzero(np.diff(key)) + 1
    for idx in np.split(np.arange(len(cand)), bounds):
        yield int(cand.ca[idx[0]]), int(cand.cb[idx[0]]), idx


def pa_mpjpe_finite(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """(S,) PA-MPJPE (units of Y) of X (S,J,3) similarity-aligned onto Y (S,J,3), finite input.

    The same Umeyama alignment as core.procrustes.pa_mpjpe (rotation with reflection guard,
    translation, uniform scale) without its mask/NaN handling, which validated detections do
    not need: one stacked SVD of the 3x3 covariances. Fewer than 3 joints do not fix a
    similarity (any two point pairs align exactly), so the cost is NaN (= gated) then.
    """
    if X.shape[1] < 3:
        return np.full(X.shape[0], np.nan)
    Xc = X - X.mean(axis=1, keepdims=True)
    Yc = Y - Y.mean(axis=1, keepdims=True)
    U, S, Vt = np.linalg.svd(np.matmul(Yc.transpose(0, 2, 1), Xc))
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    R = np.matmul(U, Vt)
    var = np.einsum("sjk,sjk->s", Xc, Xc)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(var > 0, (S[:, 0] + S[:, 1] + d * S[:, 2]) / var, 0.0)
    aligned = scale[:, None, None] * np.matmul(Xc, R.transpose(0, 2, 1))
    return np.linalg.norm(aligned - Yc, axis=2).mean(axis=1)


def _pair_costs(frames: dict[int, FrameDetections], ca, di, cb, dj) -> np.ndarray:
    """(S,) PA-MPJPE (m) of detection (ca, di) aligned onto (cb, dj)."""
    if len(ca) == 0:
        return np.zeros(0)
    J = next(fd.num_joints for fd in frames.values() if fd.n)
    X = np.empty((len(ca), J, 3))
    Y = np.empty((len(ca), J, 3))
    for c, fd in frames.items():
        sel = ca == c
        X[sel] = fd.kpts3d[di[sel]]
        sel = cb == c
        Y[sel] = fd.kpts3d[dj[sel]]
    return pa_mpjpe_finite(X, Y)


def _match(cand: _Candidates, costs: np.ndarray, kept: dict[int, np.ndarray]) -> np.ndarray:
    """Indices into cand of the Hungarian matches (per camera pair; gated pairs never match)."""
    matched = []
    for a, b, idx in _groups(cand):
        M = np.full((kept[a].size, kept[b].size), _GATED)
        c = costs[idx]
        ok = np.isfinite(c)
        M[cand.pi[idx[ok]], cand.pj[idx[ok]]] = c[ok]
        rows, cols = linear_sum_assignment(M)
        real = M[rows, cols] < _GATED
        lookup = np.full(M.shape, -1, dtype=np.int64)
        lookup[cand.pi[idx], cand.pj[idx]] = idx
        matched.append(lookup[rows[real], cols[real]])
    return np.concatenate(matched) if matched else np.zeros(0, dtype=np.int64)


def _union_find(edges: np.ndarray) -> list[np.ndarray]:
    """Connected components (sorted node arrays, sorted by first node) of an (E,2) edge list."""
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for u, v in edges.tolist():
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[max(ru, rv)] = min(ru, rv)
    comps: dict[int, list[int]] = {}
    for x in parent:
        comps.setdefault(find(x), []).append(x)
    return sorted((np.array(sorted(m), dtype=np.int64) for m in comps.values()),
                  key=lambda m: int(m[0]))


def _member_costs(frames: dict[int, FrameDetections], members: list[np.ndarray],
                  known: dict[tuple[int, int, int, int], float]) -> list[np.ndarray]:
    """Per cluster, the symmetric (M,M) PA-MPJPE matrix (m) of its members (NaN diagonal);
    entry (m, n), m < n, aligns member m onto member n. Costs already computed for the
    matching (``known``, keyed (cam, det, cam, det)) are reused; the rest in one batch."""
    tri = [np.triu_indices(len(m), 1) for m in members]
    first = np.concatenate([m[t[0]] for m, t in zip(members, tri)] or [np.zeros((0, 2), int)])
    second = np.concatenate([m[t[1]] for m, t in zip(members, tri)] or [np.zeros((0, 2), int)])
    keys = list(zip(first[:, 0].tolist(), first[:, 1].tolist(), second[:, 0].tolist(),
                    second[:, 1].tolist()))
    flat = np.array([known.get(k, np.nan) for k in keys], dtype=np.float64)
    todo = np.flatnonzero([k not in known for k in keys])
    if todo.size:
        flat[todo] = _pair_costs(frames, first[todo, 0], first[todo, 1], second[todo, 0],
                                 second[todo, 1])
    out, k = [], 0
    for m, (r, c) in zip(members, tri):
        C = np.full((len(m), len(m)), np.nan)
        C[r, c] = C[c, r] = flat[k:k + r.size]
        k += r.size
        out.append(C)
    return out


def _mean_to_rest(C: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """(M,) mean cost of each member to the other alive members, ignoring NaN (NaN if none)."""
    use = alive[None, :] & ~np.eye(len(alive), dtype=bool) & np.isfinite(C)
    n = use.sum(axis=1)
    total = np.where(use, C, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _resolve_conflicts(members: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, int]:
    """Drop, one at a time, the same-camera member with the highest mean cost to the rest.

    Returns (alive mask, number dropped). A member whose mean cost is NaN counts as worst.
    """
    alive = np.ones(len(members), dtype=bool)
    dropped = 0
    while True:
        cams, counts = np.unique(members[alive, 0], return_counts=True)
        dup = cams[counts > 1]
        if dup.size == 0:
            return alive, dropped
        cand = np.flatnonzero(alive & np.isin(members[:, 0], dup))
        mean = _mean_to_rest(C, alive)[cand]
        worst = cand[int(np.argmax(np.where(np.isnan(mean), np.inf, mean)))]
        alive[worst] = False
        dropped += 1


# ---------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------
STAT_KEYS = ("pairs_considered", "rejected_score", "rejected_reproj", "rejected_epipolar",
             "matched_pairs", "conflicts_removed", "clusters_below_k_min", "t_reproj_ms",
             "t_epipolar_ms", "t_cost_ms", "t_match_ms", "t_cluster_ms", "t_total_ms")


def associate(rig: Rig, frames: Mapping[str, FrameDetections],
              params: AssociationParams) -> AssociationResult:
    """MAEM stage 2 on one synchronised frame set (frames keyed by camera name; absent = missing).

    Returns clusters (members index the detections as given) and per-stage stats: pair counts
    (considered, rejected by score / reprojection / epipolar gate, matched), conflicts removed,
    clusters below k_min, and the time of each stage in ms.
    """
    t_start = time.perf_counter()
    stats: dict[str, float] = dict.fromkeys(STAT_KEYS, 0.0)
    by_index = _check_frames(rig, frames, params)
    P, F = _geometry(rig)
    kept = {c: np.flatnonzero(fd.scores >= params.tau_det) for c, fd in by_index.items()}
    stats["epipolar_points_fraction"] = 0.0
    stats["detections"] = float(sum(fd.n for fd in by_index.values()))
    stats["detections_kept"] = float(sum(k.size for k in kept.values()))
    cand = _enumerate_pairs(by_index, kept, stats)

    t = time.perf_counter()
    if params.reproj_gate and len(cand):
        keep = _reprojection_gate(cand, by_index, P, params)
        stats["rejected_reproj"] = float(np.count_nonzero(~keep))
        cand = cand.select(keep)
    stats["t_reproj_ms"], t = _lap(t)

    if params.epipolar_gate != "none" and len(cand):
        keep = _epipolar_gate(cand, by_index, F, params, stats)
        stats["rejected_epipolar"] = float(np.count_nonzero(~keep))
        cand = cand.select(keep)
    stats["t_epipolar_ms"], t = _lap(t)

    costs = _pair_costs(by_index, cand.ca, cand.di, cand.cb, cand.dj)
    stats["t_cost_ms"], t = _lap(t)

    matched = _match(cand, costs, kept)
    stats["matched_pairs"] = float(matched.size)
    stats["t_match_ms"], t = _lap(t)

    known = dict(zip(zip(cand.ca.tolist(), cand.di.tolist(), cand.cb.tolist(), cand.dj.tolist()),
                     costs.tolist()))
    clusters = _cluster(by_index, cand.select(matched), known, params, stats)
    stats["clusters"] = float(len(clusters))
    stats["t_cluster_ms"], _ = _lap(t)
    stats["t_total_ms"] = (time.perf_counter() - t_start) * 1e3
    return AssociationResult(clusters=clusters, stats=stats)


def _cluster(frames: dict[int, FrameDetections], matches: _Candidates,
             known: dict[tuple[int, int, int, int], float], params: AssociationParams,
             stats: dict[str, float]) -> list[Cluster]:
    """Union-find over matches, same-camera conflict removal, k_min."""
    base = 1 << 20  # node id = camera * base + detection (detections per camera < 2^20)
    edges = np.stack([matches.ca * base + matches.di, matches.cb * base + matches.dj], axis=1)
    members = [np.stack([m // base, m % base], axis=1) for m in _union_find(edges)]
    out = []
    for m, C in zip(members, _member_costs(frames, members, known)):
        alive, dropped = _resolve_conflicts(m, C)
        stats["conflicts_removed"] += dropped
        if alive.sum() < params.k_min:
            stats["clusters_below_k_min"] += 1
            continue
        out.append(Cluster(members=m[alive], costs=_mean_to_rest(C, alive)[alive]))
    return sorted(out, key=lambda c: tuple(c.members[0].tolist()))


def _lap(t: float) -> tuple[float, float]:
    now = time.perf_counter()
    return (now - t) * 1e3, now
