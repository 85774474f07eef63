"""Numba kernels of the consistent clustering (core.association.clustering): the merge check, the
cluster-level table update and the greedy merge rounds that use both.

The check and the update walk what the numpy paths compute with whole-array passes, per
candidate and joint (the check) or per merged row and column (the update), in the same
float64 operations and order (no fast-math). The one difference is the order of the 4-term
dot products of the reprojection (numpy hands them to a BLAS matmul): a relative difference
of ~1e-16 in the pixel errors the check compares with tau_verify.

The merge rounds (``greedy_merges``) take every decision of clustering._greedy_merges from
the same numbers: the gains are read from the same cluster-level tables (updated by the same
``_absorb``), the candidates are checked by the same ``_consistent`` with their members in the
same order (so the DLT sums are the same), and the best-first order is the same stable sort.
The frame set's gain tables (``gain_tables``: assignments and one subtraction) and the local
moves' sums per cluster (``cluster_sums``: the same additions in the same order) are the
numpy values too.
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.multiview_kernel import SINGULAR, adjugate, cofactors, view_entries
from maem_ros.core.jit import have_numba, jit


def consistent(
    E: np.ndarray, P: np.ndarray, uv: np.ndarray, usable: np.ndarray, rows: np.ndarray, tau: float
) -> np.ndarray:
    """(K,) whether every member of candidate k (rows[k], -1 = padding) has a median
    reprojection error (px, over its usable joints) under tau, the joints triangulated (DLT)
    from all members: clustering._Verifier's check.

    E (9,R,Jb) each row's DLT normal entries (0 where unusable), P (R,3,4) rectified
    projections, uv (R,Jb,2) px, usable (R,Jb) bool, rows (K,M) int64 < R.
    """
    ok = np.empty(rows.shape[0], np.bool_)
    _consistent(E, P, uv, usable, np.ascontiguousarray(rows, np.int64), float(tau), ok)
    return ok


def verifier_entries(P: np.ndarray, uv: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(9,R,Jb) clustering._Verifier's E: each row's DLT normal entries
    (geometry.normal_entries' float64 operations, in one compiled pass instead of ~40 numpy
    passes over small arrays), 0 where unusable. P (R,3,4), uv (R,Jb,2), usable (R,Jb)."""
    E = np.empty((9,) + usable.shape)
    _verifier_entries(
        np.ascontiguousarray(P, np.float64),
        np.ascontiguousarray(uv, np.float64),
        np.ascontiguousarray(usable, np.bool_),
        E,
    )
    return E


def absorb(x: np.ndarray, y: np.ndarray, between: np.ndarray, support: np.ndarray) -> None:
    """Clusters y[k] merged into x[k] (all distinct) in the symmetric (N,N) tables between
    (float64) and support (int64), in place: rows x += rows y, then columns x += columns y,
    rows and columns y zeroed (clustering._absorb's matrix update; greedy_merges applies it
    to the live clusters only)."""
    x, y = np.ascontiguousarray(x, np.int64), np.ascontiguousarray(y, np.int64)
    every = np.arange(between.shape[0])
    _absorb(x, y, every, between)
    _absorb(x, y, every, support)


def greedy_merges(
    links: np.ndarray,
    between: np.ndarray,
    support: np.ndarray,
    camset: np.ndarray,
    size: np.ndarray,
    label: np.ndarray,
    min_support: float,
    E: np.ndarray,
    P: np.ndarray,
    uv: np.ndarray,
    usable: np.ndarray,
    tau: float,
) -> tuple[np.ndarray, int, int]:
    """clustering._greedy_merges' rounds: (labels after the last round, merges applied, merges
    the check refused).

    links: ascending codes A * N + B (A < B) of the clusters linked by a pair that passed
    all; between (N,N) float64 summed gain and support (N,N) int geometric pairs between
    clusters, camset (N,C) bool cameras per cluster, size (N,) int64 members per cluster, all
    indexed by label and updated in place; label (N,) int64 each row's cluster (not
    modified); min_support fraction; E, P, uv, usable, tau: the merge check's inputs (see
    ``consistent``)."""
    label = np.array(label, np.int64)  # a copy: the rounds relabel it in place
    counts = np.zeros(2, np.int64)
    _greedy(
        np.ascontiguousarray(links, np.int64),
        between,
        support,
        camset,
        size,
        label,
        float(min_support),
        E,
        P,
        uv,
        usable,
        float(tau),
        counts,
    )
    return label, int(counts[0]), int(counts[1])


def move_scores(
    G: np.ndarray,
    S: np.ndarray,
    label: np.ndarray,
    camset: np.ndarray,
    cam: np.ndarray,
    refused: np.ndarray,
    size: np.ndarray,
    min_support: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """clustering._move_scores' (into, d_best, leave) in one pass over the (N,K) tables
    (the same subtractions and comparisons; the first best cluster as np.argmax picks it)."""
    N = label.size
    into, d_best, leave = np.empty(N), np.empty(N, np.int64), np.empty(N)
    _move_scores(
        G,
        S,
        np.ascontiguousarray(label, np.int64),
        camset,
        np.ascontiguousarray(cam, np.int64),
        refused,
        size,
        float(min_support),
        into,
        d_best,
        leave,
    )
    return into, d_best, leave


def cluster_sums(matrix: np.ndarray, label: np.ndarray, k: int) -> np.ndarray:
    """(N, k) float64: clustering._cluster_sums of matrix (N,N) float64 or bool over the
    clusters label (N,) ints < k: per row, the columns of each cluster added in ascending
    order from 0.0."""
    out = np.zeros((matrix.shape[0], k))
    _cluster_sums(matrix, np.ascontiguousarray(label, np.int64), out)
    return out


def gain_tables(
    i: np.ndarray,
    j: np.ndarray,
    stage: np.ndarray,
    cost: np.ndarray,
    offsets: np.ndarray,
    n: int,
    tau: float,
    rejected: float,
    capped: float,
    passed: int,
    rejected_cost: int,
) -> tuple[np.ndarray, np.ndarray]:
    """clustering._gain_matrix's (gain (n,n) float64, geometric (n,n) bool) from the pairs
    (rows i, j, stage, cost m), in one pass: geometric where stage is ``passed`` or
    ``rejected_cost``; gain tau - cost (passed), ``capped`` (cost cap), ``rejected`` (any
    other cross pair), 0 within a camera (rows offsets[c]:offsets[c + 1]) and on the
    diagonal; the values are the numpy path's (the same subtraction, constants given)."""
    gain = np.empty((n, n))
    geometric = np.empty((n, n), np.bool_)
    _gain_tables(
        i,
        j,
        stage,
        cost,
        np.ascontiguousarray(offsets, np.int64),
        float(tau),
        float(rejected),
        float(capped),
        passed,
        rejected_cost,
        gain,
        geometric,
    )
    return gain, geometric


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernels now. No-op without numba."""
    if not have_numba():
        return
    E = verifier_entries(np.zeros((2, 3, 4)), np.zeros((2, 3, 2)), np.ones((2, 3), bool))
    consistent(E, np.zeros((2, 3, 4)), np.zeros((2, 3, 2)), np.zeros((2, 3), bool), np.array([[0, -1]]), 1.0)
    absorb(np.array([0]), np.array([1]), np.zeros((2, 2)), np.zeros((2, 2), np.int64))
    greedy_merges(
        np.array([1]),
        np.ones((2, 2)),
        np.ones((2, 2), np.int32),
        np.eye(2, dtype=bool),
        np.ones(2, np.int64),
        np.arange(2),
        0.5,
        E,
        np.zeros((2, 3, 4)),
        np.zeros((2, 3, 2)),
        np.zeros((2, 3), bool),
        1.0,
    )
    move_scores(
        np.zeros((2, 2)),
        np.zeros((2, 2)),
        np.arange(2),
        np.eye(2, dtype=bool),
        np.arange(2),
        np.zeros((2, 2), bool),
        np.ones(2),
        0.5,
    )
    cluster_sums(np.eye(2, dtype=bool), np.arange(2), 2)
    cluster_sums(np.eye(2), np.arange(2), 2)
    gain_tables(
        np.array([0]),
        np.array([1]),
        np.zeros(1, np.int8),
        np.zeros(1),
        np.array([0, 1, 2]),
        2,
        1.0,
        -0.25,
        0.0,
        0,
        3,
    )


@jit
def _verifier_entries(P, uv, usable, E):
    for r in range(P.shape[0]):
        view_entries(P[r], uv[r, :, 0], uv[r, :, 1], usable[r], E[:, r])
        for j in range(usable.shape[1]):
            if not usable[r, j]:
                E[:, r, j] = 0.0


@jit
def _consistent(E, P, uv, usable, rows, tau, ok):
    Jb = E.shape[2]
    M = rows.shape[1]
    X = np.empty((Jb, 3))
    err = np.empty(Jb)
    n = np.empty(9)
    for k in range(rows.shape[0]):
        for j in range(Jb):  # the joints of all members (geometry.solve_normal)
            n[:] = 0.0
            for m in range(M):
                r = rows[k, m]
                if r >= 0:
                    for q in range(9):
                        n[q] += E[q, r, j]
            X[j, 0], X[j, 1], X[j, 2] = _solve(n)
        good = True
        for m in range(M):
            r = rows[k, m]
            if r < 0 or not good:
                continue
            count = 0
            for j in range(Jb):  # insertion sort of the usable joints' errors (a handful)
                if usable[r, j]:
                    e = _reprojection(P, r, X[j, 0], X[j, 1], X[j, 2], uv[r, j, 0], uv[r, j, 1])
                    at = count
                    while at > 0 and err[at - 1] > e:
                        err[at] = err[at - 1]
                        at -= 1
                    err[at] = e
                    count += 1
            if count == 0:
                good = False
                continue
            med = 0.5 * (err[(count - 1) // 2] + err[count // 2])
            good = med < tau
        ok[k] = good


@jit(inline=True)
def _solve(n):
    """geometry.solve_normal of one system's entries n (9,): (x, y, z), NaN if singular."""
    cof = cofactors(n[0], n[1], n[2], n[3], n[4], n[5])
    det, trace = cof[6], cof[7]
    if not abs(det) > SINGULAR * trace * trace * trace:
        det = np.nan
    return adjugate(cof[:6], det, n[6], n[7], n[8])


@jit(inline=True)
def _reprojection(P, r, x, y, z, u, v):
    """geometry.reprojection_error of point (x, y, z) in view P[r] against (u, v) px: inf
    behind the camera or for non-finite input."""
    depth = P[r, 2, 0] * x + P[r, 2, 1] * y + P[r, 2, 2] * z + P[r, 2, 3]
    inv_z = 1.0 / depth
    du = (P[r, 0, 0] * x + P[r, 0, 1] * y + P[r, 0, 2] * z + P[r, 0, 3]) * inv_z
    du -= u
    du *= du
    dv = (P[r, 1, 0] * x + P[r, 1, 1] * y + P[r, 1, 2] * z + P[r, 1, 3]) * inv_z
    dv -= v
    dv *= dv
    e = np.sqrt(du + dv)
    if depth > 0 and np.isfinite(e):
        return e
    return np.inf


@jit
def _absorb(x, y, live, matrix):
    """Rows and columns y[k] added to x[k], then zeroed. The columns of rows that are not
    live are zero (zeroed when their cluster was absorbed) and stay so: the column updates
    skip them, the same table; the row updates run over every column, where a dead one adds
    0 to 0, as contiguous loops that vectorise."""
    n = matrix.shape[1]
    for k in range(x.size):
        for c in range(n):
            matrix[x[k], c] += matrix[y[k], c]
    # columns after all rows (the entry of two merged clusters sums 4 parts), row by row (the
    # columns are strided); a column y is read, then zeroed
    for r in live:
        for k in range(x.size):
            matrix[r, x[k]] += matrix[r, y[k]]
            matrix[r, y[k]] = 0
    for k in range(x.size):
        for c in range(n):
            matrix[y[k], c] = 0


@jit
def _greedy(links, between, support, camset, size, label, min_support, E, P, uv, usable, tau, counts):
    """The rounds of clustering._greedy_merges (see greedy_merges); counts[0] += merges,
    counts[1] += refused merges."""
    n = label.size
    # codes of verified-inconsistent (A, B, sizes); -1 is no code (seeds the set's type)
    refused = {np.int64(-1)}
    while links.size > 0:
        a, b, gain, code = _candidates(links, between, support, camset, size, min_support, refused)
        if a.size == 0:
            break
        taken = _verified_disjoint(
            a, b, _descending_order(gain), code, size, label, E, P, uv, usable, tau, refused, counts
        )
        if taken.size == 0:
            break
        x, y = a[taken], b[taken]
        into = np.arange(n)
        into[y] = x
        for r in range(n):  # the merges touch disjoint clusters: one relabelling
            label[r] = into[label[r]]
        links = _relabel_links(links, into, n)
        live = np.flatnonzero(size)  # clusters before the merges (the others are empty)
        _absorb(x, y, live, between)
        _absorb(x, y, live, support)
        size[x] += size[y]
        size[y] = 0
        for k in range(x.size):
            camset[x[k]] |= camset[y[k]]
            camset[y[k]] = False
        counts[0] += x.size


@jit
def _candidates(links, between, support, camset, size, min_support, refused):
    """(a, b, gain, code) of the allowed merges, in link order: the two clusters share no
    camera, at least min_support of their cross pairs passed the geometric gates, the merge
    was not refused with these sizes (code: clustering._greedy_merges' refusal code), and
    the summed gain of the cross pairs is positive."""
    n = size.size
    a = np.empty(links.size, np.int64)
    b = np.empty(links.size, np.int64)
    gain = np.empty(links.size)
    code = np.empty(links.size, np.int64)
    m = 0
    any_refused = len(refused) > 1  # beyond the seed: else no lookup
    for k in range(links.size):
        A, B = links[k] // n, links[k] % n
        if not between[A, B] > 0 or not support[A, B] / (size[A] * size[B]) >= min_support:
            continue
        shared = False
        for c in range(camset.shape[1]):
            if camset[A, c] and camset[B, c]:
                shared = True
                break
        if shared:
            continue
        key = ((A * n + B) * (n + 1) + size[A]) * (n + 1) + size[B]
        if any_refused and key in refused:
            continue
        a[m], b[m], gain[m], code[m] = A, B, between[A, B], key
        m += 1
    return a[:m], b[:m], gain[:m], code[:m]


@jit
def _verified_disjoint(a, b, order, code, size, label, E, P, uv, usable, tau, refused, counts):
    """clustering._verified_disjoint of the candidates (a[k], b[k]) in the given order: the
    indices taken, in that order; the codes of the merges the check refused go into
    ``refused`` and their number onto counts[1]."""
    alive = np.ones(a.size, np.bool_)
    checked = size[a] + size[b] < 3
    while True:
        taken = _take_disjoint(a, b, order, alive, label.size)
        todo = taken[~checked[taken]]
        if todo.size == 0:
            return taken
        good = np.empty(todo.size, np.bool_)
        _consistent(E, P, uv, usable, _member_rows(a[todo], b[todo], label), tau, good)
        failed = 0
        for k in range(todo.size):
            checked[todo[k]] = True
            if not good[k]:
                alive[todo[k]] = False
                refused.add(code[todo[k]])
                failed += 1
        counts[1] += failed
        if failed == 0:
            return taken


@jit
def _take_disjoint(a, b, order, alive, n):
    """Indices k of clustering._disjoint_greedy over the alive edges (a[k], b[k]) in the given
    order: the sequential pass its rounds reproduce (an edge is taken unless an end is
    taken), in that order."""
    used = np.zeros(n, np.bool_)
    taken = np.empty(a.size, np.int64)
    m = 0
    for k in order:
        if alive[k] and not used[a[k]] and not used[b[k]]:
            used[a[k]] = used[b[k]] = True
            taken[m] = k
            m += 1
    return taken[:m]


@jit
def _member_rows(a, b, label):
    """(K, M) table rows of clusters a[k] and b[k] (labels), -1 padded, as
    clustering._members_padded lists them (the check sums the DLT systems in this order):
    a's rows ascending, then b's."""
    n = label.size
    start = np.zeros(n + 1, np.int64)  # rows grouped by label, ascending within each
    for r in range(n):
        start[label[r] + 1] += 1
    for lab in range(n):
        start[lab + 1] += start[lab]
    order = np.empty(n, np.int64)
    fill = start[:n].copy()
    for r in range(n):
        order[fill[label[r]]] = r
        fill[label[r]] += 1
    count = start[a + 1] - start[a] + start[b + 1] - start[b]
    rows = np.full((a.size, count.max() if a.size else 0), -1, np.int64)
    for k in range(a.size):
        at = 0
        for lab in (a[k], b[k]):
            for s in range(start[lab], start[lab + 1]):
                rows[k, at] = order[s]
                at += 1
    return rows


@jit
def _relabel_links(links, into, n):
    """clustering._relabel_links: codes after relabelling, ascending, each once, none within
    one cluster. Sorted by two stable counting passes (by b, then by a; both < n) rather
    than np.sort, which numba compiles to a quicksort 10x slower than numpy's."""
    a = np.empty(links.size, np.int64)
    b = np.empty(links.size, np.int64)
    m = 0
    for k in range(links.size):
        p, q = into[links[k] // n], into[links[k] % n]
        if p != q:
            a[m], b[m] = min(p, q), max(p, q)
            m += 1
    by_b = _counting_order(b[:m], np.arange(m), n)
    by_ab = _counting_order(a[:m], by_b, n)
    out = np.empty(m, np.int64)
    u = 0
    for k in by_ab:
        code = a[k] * n + b[k]
        if u == 0 or out[u - 1] != code:
            out[u] = code
            u += 1
    return out[:u]


@jit
def _counting_order(key, order, n):
    """order (indices into key, keys < n) stably reordered by key."""
    start = np.zeros(n + 1, np.int64)
    for k in order:
        start[key[k] + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    out = np.empty(order.size, np.int64)
    for k in order:
        out[start[key[k]]] = k
        start[key[k]] += 1
    return out


@jit
def _descending_order(g):
    """np.argsort(-g, kind="stable") of positive finite g: g descending, ties in index order.

    An LSD radix sort (stable) of the bits of g, inverted: for positive floats the bits
    ascend with the value. Faster than numba's argsort(kind="mergesort") on the thousands of
    candidates of a first round (linear in n): 6 passes of 11 bits, the histograms counted in
    one read, the passes where every key has the same digit (most of the exponent's) skipped."""
    n = g.size
    key = np.empty(n, np.uint64)
    count = np.zeros((6, 2049), np.int64)
    bits = np.ascontiguousarray(g).view(np.uint64)
    for k in range(n):
        key[k] = ~bits[k]
        for p in range(6):
            count[p, ((key[k] >> np.uint64(11 * p)) & np.uint64(2047)) + np.uint64(1)] += 1
    order = np.arange(n)
    spare = np.empty(n, np.int64)
    for p in range(6):
        if count[p].max() == n:  # one digit for all: the pass keeps the order
            continue
        for v in range(2048):
            count[p, v + 1] += count[p, v]
        for k in order:
            digit = (key[k] >> np.uint64(11 * p)) & np.uint64(2047)
            spare[count[p, digit]] = k
            count[p, digit] += 1
        order, spare = spare, order
    return order


@jit
def _move_scores(G, S, label, camset, cam, refused, size, min_support, into, d_best, leave):
    for i in range(label.size):
        own = G[i, label[i]]
        best = -np.inf
        at = 0
        for k in range(G.shape[1]):
            if camset[k, cam[i]] or refused[i, k] or not size[k] > 0 or not S[i, k] >= min_support * size[k]:
                continue
            d = G[i, k] - own
            if d > best:  # strict: the first of equal ones, as np.argmax
                best = d
                at = k
        into[i] = best
        d_best[i] = at
        leave[i] = -own if size[label[i]] > 1 else -np.inf


@jit
def _cluster_sums(matrix, label, out):
    for i in range(matrix.shape[0]):
        for j in range(matrix.shape[1]):
            out[i, label[j]] += matrix[i, j]


@jit
def _gain_tables(i, j, stage, cost, offsets, tau, rejected, capped, passed, rejected_cost, gain, geometric):
    gain[:] = rejected
    geometric[:] = False
    for k in range(i.size):
        if stage[k] == passed or stage[k] == rejected_cost:
            a, b = i[k], j[k]
            geometric[a, b] = geometric[b, a] = True
            gain[a, b] = gain[b, a] = tau - cost[k] if stage[k] == passed else capped
    for c in range(offsets.size - 1):  # rows are grouped by camera
        gain[offsets[c] : offsets[c + 1], offsets[c] : offsets[c + 1]] = 0.0
