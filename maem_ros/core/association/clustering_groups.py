"""Clusters as groups of detection-table rows (``Found``), and the two clusterings that build
whole groups at once: the paper's (Hungarian matches per camera pair, union-find, conflict
removal) and the spectral baseline (PA-MPJPE matching). The default consistent clustering is in
clustering.py; ``clustering`` dispatches on ``params.clustering``."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.optimize import linear_sum_assignment

from maem_ros.core.detections import camera_pair_groups

#: (rows_a, rows_b) -> pose costs (m) of those detection pairs, aligned a onto b
PairCost = Callable[[np.ndarray, np.ndarray], np.ndarray]


#: spectral baseline affinity width (m): about the body-joint PA-MPJPE of one person's
#: detections in two views (see the simulator's noise model), so that same-person weights
#: stay near 1 and different-person weights fall towards 0
SPECTRAL_SIGMA = 0.05


@dataclass
class Found:
    """Clusters as table rows (sorted arrays, before k_min) and rows dropped as conflicts."""

    groups: list[np.ndarray]
    conflicts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def groups_of(label: np.ndarray) -> list[np.ndarray]:
    """Sorted row arrays of each label, ordered by first row."""
    order = np.argsort(label, kind="stable")  # rows ascending within each label
    bounds = np.flatnonzero(np.diff(label[order])) + 1
    groups = [g for g in np.split(order, bounds) if g.size]
    return [groups[k] for k in np.argsort([int(g[0]) for g in groups], kind="stable").tolist()]


# ---------------------------------------------------------------------------------------
# the paper's pipeline
# ---------------------------------------------------------------------------------------
#: cost given to gated pairs in the Hungarian matrix: any real match is preferred, and
#: an assignment that lands on it is discarded
_GATED = 1e9


def paper(table, pairs, stats, pair_cost) -> Found:
    """The paper's clustering: Hungarian matches per camera pair, their connected components,
    conflicts (two detections of one camera) removed."""
    matched = _hungarian(table, pairs)
    stats["matched_pairs"] = float(matched.size)
    groups = _union_find(table, pairs.i[matched], pairs.j[matched])
    return _remove_conflicts(table, groups, stats, pair_cost)


def _hungarian(table, pairs) -> np.ndarray:
    """Indices into pairs of the Hungarian matches, per camera pair (gated pairs never match)."""
    ok = pairs.passed
    matched = []
    ca, cb = table.cam[pairs.i], table.cam[pairs.j]
    for a, b, idx in camera_pair_groups(ca, cb):
        pi = pairs.i[idx] - table.offsets[a]
        pj = pairs.j[idx] - table.offsets[b]
        M = np.full(
            (table.offsets[a + 1] - table.offsets[a], table.offsets[b + 1] - table.offsets[b]), _GATED
        )
        use = ok[idx]
        M[pi[use], pj[use]] = pairs.cost[idx[use]]
        rows, cols = linear_sum_assignment(M)
        real = M[rows, cols] < _GATED
        lookup = np.full(M.shape, -1, dtype=np.int64)
        lookup[pi, pj] = idx
        matched.append(lookup[rows[real], cols[real]])
    return np.concatenate(matched) if matched else np.zeros(0, dtype=np.int64)


def _union_find(table, u: np.ndarray, v: np.ndarray) -> list[np.ndarray]:
    """Connected components (sorted row arrays) of the match graph, singletons included."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    N = len(table)
    graph = coo_matrix((np.ones(u.size), (u, v)), shape=(N, N))
    _, label = connected_components(graph, directed=False)
    return groups_of(label)


def _remove_conflicts(table, groups, stats, pair_cost) -> Found:
    """While a group holds two detections of one camera, drop the one with the highest mean
    cost to the rest of the group (NaN counts as worst)."""
    conflicts = []
    for rows in groups:
        cams = table.cam[rows]
        if np.unique(cams).size == cams.size:
            continue
        Cm = cost_matrix(rows, pair_cost)
        alive = np.ones(rows.size, bool)
        while True:
            c, counts = np.unique(cams[alive], return_counts=True)
            dup = c[counts > 1]
            if dup.size == 0:
                break
            cand = np.flatnonzero(alive & np.isin(cams, dup))
            mean = mean_to_rest(Cm, alive)[cand]
            worst = cand[int(np.argmax(np.where(np.isnan(mean), np.inf, mean)))]
            alive[worst] = False
            conflicts.append(rows[worst])
    stats["conflicts_removed"] += float(len(conflicts))
    return Found(groups, np.array(sorted(conflicts), dtype=np.int64))


def cost_matrix(rows: np.ndarray, pair_cost: PairCost) -> np.ndarray:
    """Symmetric (M,M) pair costs of the rows (entry m<n aligns m onto n), NaN diagonal."""
    r, c = np.triu_indices(rows.size, 1)
    Cm = np.full((rows.size, rows.size), np.nan)
    Cm[r, c] = Cm[c, r] = pair_cost(rows[r], rows[c])
    return Cm


def mean_to_rest(Cm: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """(...,M) mean cost of each member to the other alive members, ignoring NaN (NaN if
    none), of cost matrices Cm (...,M,M)."""
    use = alive[None, :] & ~np.eye(len(alive), dtype=bool) & np.isfinite(Cm)
    n = use.sum(axis=-1)
    total = np.where(use, Cm, 0.0).sum(axis=-1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


# ---------------------------------------------------------------------------------------
# spectral baseline (PA-MPJPE matching)
# ---------------------------------------------------------------------------------------
def spectral(table, stats, pair_cost) -> Found:
    """The spectral baseline (PA-MPJPE matching): k-means on the normalised affinity's top
    eigenvectors (k = most detections of one camera), conflicts removed as in the paper's."""
    N = len(table)
    k = int(np.diff(table.offsets).max())
    if N < 2 or k < 1:
        return Found(groups_of(np.arange(N)))
    i, j = np.triu_indices(N, 1)
    other = table.cam[i] != table.cam[j]
    i, j = i[other], j[other]
    W = np.zeros((N, N))
    w = np.exp(-((np.nan_to_num(pair_cost(i, j), nan=np.inf) / SPECTRAL_SIGMA) ** 2))
    W[i, j] = W[j, i] = w
    d = W.sum(1)
    inv = np.where(d > 0, 1.0 / np.sqrt(np.maximum(d, 1e-300)), 0.0)
    L = inv[:, None] * W * inv[None, :]
    _, vecs = np.linalg.eigh(L)
    U = vecs[:, -min(k, N) :]
    U /= np.maximum(np.linalg.norm(U, axis=1, keepdims=True), 1e-12)
    with warnings.catch_warnings():  # an emptied k-means cluster warns: simply fewer people
        warnings.simplefilter("ignore", UserWarning)
        _, label = kmeans2(U, min(k, N), minit="++", seed=np.random.default_rng(0), missing="warn")
    groups = groups_of(label)
    stats["matched_pairs"] = float(sum(g.size - 1 for g in groups))
    return _remove_conflicts(table, groups, stats, pair_cost)
