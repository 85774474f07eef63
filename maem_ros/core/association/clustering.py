"""Clustering of gated cross-view detection pairs into people (MAEM stage 2, step 5).

Input: the frame set's DetectionTable (row = detection) and its PairSet (every cross-camera
pair with the stage that rejected it and, for survivors, the pair cost in metres). Output:
groups of table rows (one per person candidate, before k_min) and, for the paper's pipeline,
the rows conflict removal dropped.

``consistent`` (default). Per-pair matching plus union-find is transitive: one wrong match
joins two people. Here every decision is taken on whole clusters:
  * objective: a cluster earns ``tau_cost - cost`` for each member pair that passed the gates
    and the cap, and pays a quarter of ``tau_cost`` for each member pair a geometric gate
    rejected (correlation clustering with the cost cap as the zero point);
  * greedy best-first merges over all camera pairs at once, in rounds: every cluster pair
    linked by a pair that passed the gates and the cap is a candidate; a merge is allowed only
    if the two share no camera, at least ``min_support`` of the new cross pairs passed the
    geometric gates, it raises the objective,
    and (from three views on) every member's median reprojection error of the body joints
    triangulated from all members is under ``tau_verify`` px; the best allowed merges that do
    not touch each other are applied, then the candidates are rebuilt;
  * local moves: a detection moves to another cluster (or alone) when that raises the
    objective and the target stays verified; this undoes early greedy mistakes, e.g. a
    detection whose true partner is absent in one camera, paired first with the closest
    other person there.
Designs read before choosing: MVPose (cycle-consistent multi-way matching of all views,
convex relaxation: global but iterative and slow for 16 views), EasyMocap's associate
(greedy growth from the best pair with view-consistency checks) and 4D association (limb
graph, greedy with consistency); the choice here is EasyMocap-like greedy growth with
MVPose-like global consistency (no camera twice, most cross pairs agree), geometric
verification as in the RANSAC triangulation, and a cheap local search, everything batched.

``paper``: Hungarian per camera pair on the gated cost, union-find over the matches, then
while a cluster holds two detections of one camera the one with the highest mean cost to the
rest is dropped (MAEM as published).

``spectral``: the seed paper's PA-MPJPE matching baseline (Hokari et al.): a complete graph
over all kept detections, weights exp(-(PA-MPJPE / sigma)^2) (0 within a camera; no
geometric gates), normalised spectral clustering into as many people as the most crowded
camera has detections, then the paper's conflict removal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

import maem_ros.core.association.clustering_kernel as clustering_kernel
from maem_ros.core.association.clustering_groups import (
    Found,
    PairCost,
    groups_of,
    paper,
    spectral,
)
from maem_ros.core.detections import PASSED, REJECTED_COST, DetectionTable, PairSet
from maem_ros.core.geometry.multiview import normal_entries, reprojection_error, solve_normal
from maem_ros.core.intsets import sorted_unique, unique_inverse

if TYPE_CHECKING:
    from maem_ros.core.association.params import AssociationParams

#: objective weight (x tau_cost) of a cross pair that a geometric gate rejected. Weak: with
#: realistic noise a true pair fails the 8 px mesh gate now and then (hard simulator noise:
#: 1 % of true pairs are above 7.6 px), and geometry is checked on the whole cluster anyway;
#: -0.25 against -1.0 raised recall on hard scenes by 2-8 points at equal medium recall
#: (3 rigs x 3 seeds; see doc/design.md §9.2)
REJECTED_PAIR_GAIN = -0.25
#: objective weight (x tau_cost) of a pair that passed the geometric gates but costs more than
#: tau_cost: it never starts a merge, and neither rewards nor penalises a cluster holding it
CAPPED_PAIR_GAIN = 0.0
#: upper bound on local moves per frame set, as a multiple of the detections (each move
#: raises the objective, so the search ends anyway; this only bounds the time)
MAX_MOVES_PER_DETECTION = 2


def cluster(
    table: DetectionTable,
    pairs: PairSet,
    P: np.ndarray,
    joints: np.ndarray,
    params: AssociationParams,
    stats: dict[str, float],
    pair_cost: PairCost,
) -> Found:
    """Cluster the table's rows with ``params.clustering`` (see the module docstring).

    P (C,3,4) the rig's rectified projections; joints: keypoint indices of the pair cost and
    of the consistent clustering's merge check."""
    if len(table) == 0:
        return Found([])
    if params.clustering == "paper":
        return paper(table, pairs, stats, pair_cost)
    if params.clustering == "spectral":
        return spectral(table, stats, pair_cost)
    kernels = _kernels(params.execution.backend)
    return _consistent(
        table, pairs, _Verifier(table, P, joints, params.tau_verify, kernels), params, stats, kernels
    )


def _kernels(backend: str):
    """core/association/clustering_kernel.py when ``backend`` runs numba (auto: when installed), else None
    (the numpy paths: the same results)."""
    if backend == "numba" and not clustering_kernel.have_numba():
        raise ValueError("backend: 'numba' requested but numba is not installed")
    return clustering_kernel if backend != "numpy" and clustering_kernel.have_numba() else None


# ---------------------------------------------------------------------------------------
# consistent clustering
# ---------------------------------------------------------------------------------------
class _Verifier:
    """Batched cluster check: body joints triangulated (DLT) from all members, each member's
    median reprojection error (px) must stay under tau_verify."""

    def __init__(self, table: DetectionTable, P: np.ndarray, joints: np.ndarray, tau: float, kernels=None):
        # one extra row N stands for padding: no usable joint, zero DLT share
        N, Jb = len(table), joints.size
        self.uv = np.zeros((N + 1, Jb, 2))
        self.uv[:N] = table.kpts2d[:, joints]
        self.P = np.zeros((N + 1, 3, 4))
        self.P[:N] = P[table.cam]
        self.tau = tau
        self.usable = np.zeros((N + 1, Jb), bool)
        self.usable[:N] = np.isfinite(self.uv[:N]).all(-1)
        # each row's share of every candidate cluster's DLT system, computed once per frame
        # set (unusable joints weigh 0): (9,N+1,Jb)
        self.E = (
            normal_entries(self.P[:, None], self.uv, self.usable) * self.usable
            if kernels is None
            else kernels.verifier_entries(self.P, self.uv, self.usable)
        )
        self.kernels = kernels  # clustering_kernel (numba) or None (numpy)

    def __call__(self, rows: np.ndarray) -> np.ndarray:
        """rows (K,M) table rows, -1 = padding -> (K,) all members consistent."""
        if rows.size == 0:
            return np.zeros(rows.shape[0], bool)
        if self.kernels is not None:
            return self.kernels.consistent(self.E, self.P, self.uv, self.usable, rows, self.tau)
        # members first, in their order (padding may sit anywhere), then drop padding columns
        rows = np.take_along_axis(rows, np.argsort(rows < 0, axis=1, kind="stable"), 1)
        rows = rows[:, : int((rows >= 0).sum(1).max())]
        present = rows >= 0
        r = np.where(present, rows, self.usable.shape[0] - 1)
        P = self.P[r]  # (K,M,3,4)
        uv = self.uv[r]  # (K,M,Jb,2)
        usable = self.usable[r]
        E = self.E[:, r]  # (9,K,M,Jb), padding = 0
        X = solve_normal(E.sum(2))  # (K,Jb,3)
        err = reprojection_error(P, X[:, None], uv)[:, :, 0]  # (K,M,Jb), inf if unusable
        err = np.where(usable, err, np.inf)
        n = usable.sum(-1)  # usable joints per member
        # median over each member's usable joints: they sort first, inf (unusable) last
        srt = np.sort(err, axis=-1)
        lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
        hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
        med = np.where(n > 0, 0.5 * (lo + hi), np.inf)
        bad = present & ~(med < self.tau)
        return np.asarray(~bad.any(axis=1))  # (K,) bool (any's stubs allow a scalar)


def _gain_matrix(
    table: DetectionTable, pairs: PairSet, tau: float, kernels=None
) -> tuple[np.ndarray, np.ndarray]:
    """(gain (N,N), geometric (N,N) bool) over table rows.

    gain: tau - cost for pairs that passed everything, CAPPED_PAIR_GAIN x tau for pairs that
    passed the geometric gates but cost more than the cap, REJECTED_PAIR_GAIN x tau for cross
    pairs a geometric gate rejected, 0
    within a camera (such pairs are never together) and on the diagonal. geometric: the pair
    passed the geometric gates (the merge support counts these). kernels: clustering_kernel
    (one compiled pass over the pairs, the same tables) or None."""
    N = len(table)
    if kernels is not None:
        return kernels.gain_tables(
            pairs.i,
            pairs.j,
            pairs.stage,
            pairs.cost,
            table.offsets,
            N,
            tau,
            REJECTED_PAIR_GAIN * tau,
            CAPPED_PAIR_GAIN * tau,
            PASSED,
            REJECTED_COST,
        )
    geo = np.flatnonzero(pairs.geometric)  # a few % of the pairs: index them once
    gi, gj = pairs.i[geo], pairs.j[geo]
    geometric = np.zeros((N, N), bool)
    geometric[gi, gj] = geometric[gj, gi] = True
    gain = np.full((N, N), REJECTED_PAIR_GAIN * tau)
    gain[gi, gj] = gain[gj, gi] = np.where(
        pairs.stage[geo] == PASSED, tau - pairs.cost[geo], CAPPED_PAIR_GAIN * tau
    )
    for start, end in zip(table.offsets[:-1].tolist(), table.offsets[1:].tolist()):
        gain[start:end, start:end] = 0.0  # rows are grouped by camera
    return gain, geometric


def _consistent(
    table: DetectionTable,
    pairs: PairSet,
    verify: _Verifier,
    params: AssociationParams,
    stats: dict[str, float],
    kernels,
) -> Found:
    gain, geometric = _gain_matrix(table, pairs, params.tau_cost, kernels)
    label = np.arange(len(table))
    label = _greedy_merges(table, pairs, gain, geometric, label, verify, params, stats, kernels)
    label = _local_moves(table, gain, geometric, label, verify, params, stats, kernels)
    # each pair once: the geometric pairs i < j within one cluster
    geo = np.flatnonzero(pairs.geometric)
    stats["matched_pairs"] = float(np.count_nonzero(label[pairs.i[geo]] == label[pairs.j[geo]]))
    return Found(groups_of(label))


def _members_padded(label: np.ndarray, parts: list[np.ndarray]) -> np.ndarray:
    """(K, M) table rows of the union of the given label sets per candidate, -1 padded.

    parts: arrays (K,) of labels (-1 = none) whose members are concatenated per candidate.
    """
    order = np.argsort(label, kind="stable")
    size = np.bincount(label, minlength=label.size)
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    sizes = [np.where(p >= 0, size[np.maximum(p, 0)], 0) for p in parts]
    M = int(np.sum(sizes, axis=0).max(initial=0))
    slot = np.arange(M)[None, :]
    out = np.full((parts[0].size, M), -1, np.int64)
    base = np.zeros(parts[0].size, np.int64)
    for p, s in zip(parts, sizes):
        mine = (slot >= base[:, None]) & (slot < (base + s)[:, None])
        src = start[np.maximum(p, 0)][:, None] + slot - base[:, None]
        out[mine] = order[np.clip(src, 0, label.size - 1)][mine]
        base = base + s
    return out


def _greedy_merges(table, pairs, gain, gated, label, verify, params, stats, kernels) -> np.ndarray:
    """Best-first verified merges in rounds until no allowed merge is left.

    label: each row its own cluster (label = row). Cluster-level tables indexed by label are
    kept merged as clusters merge (a merge adds the absorbed cluster's row and column), so a
    round reads each candidate's figures instead of gathering its members' pairs."""
    C = int(table.cam.max()) + 1
    N = label.size
    # the passed pairs indexed once: a few % of all pairs (each boolean-mask gather would
    # scan all of them)
    ok = np.flatnonzero(pairs.passed)
    i, j = pairs.i[ok], pairs.j[ok]
    # codes A * N + B (A < B) of the clusters linked by a pair that passed all (merge
    # candidates), ascending: relabelled after each round (a list of the passed pairs, not an
    # N x N table that every round would scan)
    links = sorted_unique(np.minimum(i, j) * N + np.maximum(i, j))
    between = gain.copy()  # summed gain of the cross pairs of two clusters
    # cross pairs that passed the geometric gates (int32 for the kernel: the same counts in
    # half the memory its table updates stream through)
    support = gated.astype(np.int64 if kernels is None else np.int32)
    camset = np.zeros((N, C), bool)
    camset[label, table.cam] = True
    size = np.bincount(label, minlength=N)
    if kernels is not None:  # the same rounds, compiled (clustering_kernel.greedy_merges)
        label, merged, rejected = kernels.greedy_merges(
            links,
            between,
            support,
            camset,
            size,
            label,
            params.min_support,
            verify.E,
            verify.P,
            verify.uv,
            verify.usable,
            verify.tau,
        )
        stats["merges_rejected"] += float(rejected)
        stats["merges"] += float(merged)
        return label
    refused: set[int] = set()  # codes of verified-inconsistent (A, B, sizes)
    while True:
        A, B = np.divmod(links, N)
        if A.size == 0:
            return label
        disjoint = ~(camset[A] & camset[B]).any(1)
        # a refused merge stays refused while neither cluster changed (same labels and sizes)
        codes = ((A * N + B) * (N + 1) + size[A]) * (N + 1) + size[B]
        pre = disjoint & (support[A, B] / (size[A] * size[B]) >= params.min_support)
        if refused:
            pre &= ~np.isin(codes, np.fromiter(refused, np.int64, len(refused)))
        # objective change: the summed gain over all cross pairs of the two clusters
        g = between[A, B]
        cand = np.flatnonzero(pre & (g > 0))
        if cand.size == 0:
            return label
        best_first = cand[np.argsort(-g[cand], kind="stable")]
        a, b = A[best_first], B[best_first]
        taken, failed = _verified_disjoint(a, b, size, label, verify, N)
        refused.update(codes[best_first[failed]].tolist())
        stats["merges_rejected"] += float(failed.size)
        if taken.size == 0:
            return label
        x, y = a[taken], b[taken]
        into = np.arange(N)
        into[y] = x
        label = into[label]  # the applied merges touch disjoint clusters: one relabelling
        links = _relabel_links(links, into, N)
        _absorb(x, y, size, between, support, camset)
        stats["merges"] += float(x.size)


def _relabel_links(links: np.ndarray, into: np.ndarray, n: int) -> np.ndarray:
    """Link codes A * n + B (A < B) after relabelling by ``into``: ascending, each once, none
    within one cluster."""
    a, b = into[links // n], into[links % n]
    a, b = np.minimum(a, b), np.maximum(a, b)
    apart = a != b
    return sorted_unique(a[apart] * n + b[apart])


def _absorb(
    x: np.ndarray,
    y: np.ndarray,
    size: np.ndarray,
    between: np.ndarray,
    support: np.ndarray,
    camset: np.ndarray,
) -> None:
    """Clusters y[k] merged into x[k] (all distinct) in the cluster-level tables, in place
    (the numpy rounds; the compiled rounds update the matrices by clustering_kernel._absorb,
    the same sums)."""
    size[x] += size[y]
    size[y] = 0
    for matrix in (between, support):
        matrix[x] += matrix[y]  # rows first, then columns: the entry of two merged
        matrix[:, x] += matrix[:, y]  # clusters sums all four parts
        matrix[y] = 0
        matrix[:, y] = 0
    camset[x] |= camset[y]
    camset[y] = False


def _verified_disjoint(
    a: np.ndarray, b: np.ndarray, size: np.ndarray, label: np.ndarray, verify: _Verifier, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """(taken, failed) indices k of the candidate merges (a[k], b[k]) (cluster labels < n,
    best first): the best-first pass over the merges that pass the check (from three members
    on), and the merges the check refused on the way.

    Only merges the pass would take are checked: take the disjoint best-first merges of
    those not refused yet, check the unchecked ones among them, and repeat while any fails.
    A merge the pass skips (an end already taken) takes nothing, so dropping the refused
    ones it skipped does not change what it takes: the result is the pass over all merges
    that pass the check, without checking the ones it would skip anyway (a frame set of the
    large bench load: 154 checks instead of 777)."""
    alive = np.ones(a.size, bool)
    checked = size[a] + size[b] < 3  # two singletons: nothing to check
    while True:
        taken = _disjoint_greedy(a[alive], b[alive], n)
        taken = np.flatnonzero(alive)[taken]
        todo = taken[~checked[taken]]
        if todo.size == 0:
            return taken, np.flatnonzero(~alive)
        good = verify(_members_padded(label, [a[todo], b[todo]]))
        checked[todo] = True
        alive[todo[~good]] = False
        if good.all():
            return taken, np.flatnonzero(~alive)


def _disjoint_greedy(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Indices k (ascending) of the edges (a[k], b[k]) (labels < n) that a best-first pass in
    k order takes when it skips every edge touching a label already taken.

    Computed in rounds rather than edge by edge: an edge that comes first among all remaining
    edges at both of its ends is taken by the sequential pass too (nothing earlier can block
    it); taking those and dropping the edges they block repeats until none remain."""
    rank = np.arange(a.size)
    alive = np.ones(a.size, bool)
    taken = np.zeros(a.size, bool)
    used = np.zeros(n, bool)
    while alive.any():
        first = np.full(n, a.size)
        np.minimum.at(first, a[alive], rank[alive])
        np.minimum.at(first, b[alive], rank[alive])
        now = alive & (first[a] == rank) & (first[b] == rank)
        taken |= now
        used[a[now]] = used[b[now]] = True
        alive &= ~(used[a] | used[b])
    return np.flatnonzero(taken)


def _local_moves(table, gain, gated, label, verify, params, stats, kernels=None) -> np.ndarray:
    """Move single detections between clusters (or out) while that raises the objective.

    Each step scores every (detection, target) move at once, verifies the improving ones in
    one batch and applies the best that stays consistent. kernels (clustering_kernel or
    None) sums the tables per cluster in a compiled loop (the same floats)."""
    N = label.size
    C = int(table.cam.max()) + 1
    _, label = unique_inverse(label, N)
    K = int(label.max()) + 1
    G = _cluster_sums(gain, label, K, kernels)  # (N,K): objective gain with each cluster
    S = _cluster_sums(gated, label, K, kernels)  # (N,K): gated pairs with each cluster
    size = np.bincount(label, minlength=K).astype(float)
    camset = np.zeros((K, C), bool)
    camset[label, table.cam] = True
    refused = np.zeros((N, K), bool)  # verified inconsistent until the target changes
    for _ in range(MAX_MOVES_PER_DETECTION * N):
        into, d_best, leave = _move_scores(
            G, S, label, camset, table.cam, refused, size, params.min_support, kernels
        )
        cand = np.flatnonzero((into > 1e-12) | (leave > 1e-12))
        if cand.size == 0:
            break
        moves = [(float(into[d]), int(d), int(d_best[d])) for d in cand if into[d] > 1e-12]
        moves += [(float(leave[d]), int(d), -1) for d in cand if leave[d] > 1e-12]
        moves.sort(key=lambda m: -m[0])
        need = [m for m in moves if m[2] >= 0 and size[m[2]] + 1 >= 3]
        ok = {}
        if need:
            rows = _members_padded(label, [np.array([m[2] for m in need])])
            rows = np.concatenate([rows, np.array([[m[1]] for m in need])], axis=1)
            for m, good in zip(need, verify(rows)):
                ok[m[1], m[2]] = bool(good)
                if not good:
                    refused[m[1], m[2]] = True
        chosen = next((m for m in moves if m[2] < 0 or ok.get((m[1], m[2]), True)), None)
        if chosen is None:
            continue
        _, d, T = chosen
        if T < 0:
            T = int(np.flatnonzero(size == 0)[0]) if np.any(size == 0) else -1
            if T < 0:  # every label in use: grow the tables by one empty cluster
                G = np.concatenate([G, np.zeros((N, 1))], 1)
                S = np.concatenate([S, np.zeros((N, 1))], 1)
                size = np.append(size, 0.0)
                camset = np.concatenate([camset, np.zeros((1, C), bool)])
                refused = np.concatenate([refused, np.zeros((N, 1), bool)], 1)
                T = K
                K += 1
        src = label[d]
        G[:, src] -= gain[:, d]
        G[:, T] += gain[:, d]
        S[:, src] -= gated[:, d]
        S[:, T] += gated[:, d]
        size[src] -= 1
        size[T] += 1
        camset[src, table.cam[d]] = False
        camset[T, table.cam[d]] = True
        label[d] = T
        refused[:, [src, T]] = False
        stats["moves"] += 1.0
    return label


def _move_scores(
    G: np.ndarray,
    S: np.ndarray,
    label: np.ndarray,
    camset: np.ndarray,
    cam: np.ndarray,
    refused: np.ndarray,
    size: np.ndarray,
    min_support: float,
    kernels=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(into, d_best, leave) (N,) of the local moves' step: the best objective change of
    moving each detection into another cluster (-inf if none is allowed) and that cluster
    (the first best), and that of moving it out alone (-inf if alone already). G, S (N,K)
    gain and gated pairs with each cluster, label (N,), camset (K,C), cam (N,), refused
    (N,K), size (K,) float. kernels: the same numbers in one compiled pass."""
    if kernels is not None:
        return kernels.move_scores(G, S, label, camset, cam, refused, size, min_support)
    N = label.size
    own = G[np.arange(N), label]
    occupied = camset[:, cam].T  # (N,K): cluster already has this detection's camera
    allowed = ~occupied & ~refused & (size[None, :] > 0) & (S >= min_support * size[None, :])
    delta = np.where(allowed, G - own[:, None], -np.inf)
    leave = np.where(size[label] > 1, -own, -np.inf)  # move out, alone
    d_best = np.argmax(delta, axis=1)
    return delta[np.arange(N), d_best], d_best, leave


def _cluster_sums(matrix: np.ndarray, label: np.ndarray, k: int, kernels=None) -> np.ndarray:
    """(N, k) float64: per row i and cluster c < k, the sum of matrix[i, j] (N,N) over the
    rows j with label[j] == c, added in ascending j from 0.0 (a one-hot matmul would add
    them in BLAS's order, and costs an (N, k) one-hot matrix product; kernels: the same sums
    compiled)."""
    if kernels is not None:
        return kernels.cluster_sums(matrix, label, k)
    order = np.argsort(label, kind="stable")
    start = np.concatenate([[0], np.cumsum(np.bincount(label, minlength=k))])
    rank = np.empty(label.size, np.int64)  # j's place among its cluster's rows
    rank[order] = np.arange(label.size) - start[label[order]]
    out = np.zeros((matrix.shape[0], k))
    for r in range(int(rank.max(initial=-1)) + 1):  # at most one row per cluster per rank
        cols = np.flatnonzero(rank == r)
        out[:, label[cols]] += matrix[:, cols]
    return out
