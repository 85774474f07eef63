"""The epipolar gate's per-block arithmetic in numba (imported only when numba is installed):
float64 and float32 SIMD distance sums of a block of points (one pair, or two pairs of one
detection), block coordinate ranges, the float32 sums' rigorous rounding-error bound, and the
per-pair steps of the frame kernel (epipolar_kernel) that settle, exit early or retry a pair.
The arithmetic and its bound are documented in core.association.gates.epipolar.
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.association.gates.epipolar_constants import (
    BOUND_SLACK,
    EPIPOLE_NORM,
    RSQRT_ERR,
    RSQRT_ERR_REFINED,
    U32,
)
from maem_ros.core.association.gates.epipolar_jit import (
    estimated_rsqrt,
    inline,
    inline32,
    jit,
    jit32,
    plain,
    points,
    prefetch_l2,
    wide_vectors,
)
from maem_ros.core.association.gates.epipolar_ranges import block_range

#: squared line norm at (or below) which a point is at the epipole (F of unit norm)
_Q_EPIPOLE = EPIPOLE_NORM**2


@jit
def inv_sqrt(q):
    """1/sqrt(q) to ~1e-13 relative: a float32 estimate refined by one Newton step in
    float64 (float64 sqrt and division are the slow units). inf at the epipole
    (q <= EPIPOLE_NORM^2; F has unit norm, so the float32 estimate is in range), NaN for
    NaN."""
    y = np.float64(np.float32(1.0) / np.sqrt(np.float32(max(q, _Q_EPIPOLE))))
    y = y * (1.5 - 0.5 * q * y * y)
    return y if q > _Q_EPIPOLE else np.inf


@jit
def block64(a, b, fs, fk, ha, symmetric):
    """(sum of d_k, points used) of a block, float64: points a, b (2m,) rectified px, fs[fk]
    (9,) unit F; missing points (NaN) take no part; a point at the epipole makes the sum
    NaN or inf."""
    wide_vectors()
    f = fs[fk]
    part = 0.0
    used = 0
    for k in range(a.shape[0] // 2):
        ua = np.float64(a[2 * k])
        va = np.float64(a[2 * k + 1])
        ub = np.float64(b[2 * k])
        vb = np.float64(b[2 * k + 1])
        l0 = f[0] * ua + f[1] * va + f[2]
        l1 = f[3] * ua + f[4] * va + f[5]
        l2 = f[6] * ua + f[7] * va + f[8]
        w = ha * inv_sqrt(l0 * l0 + l1 * l1)
        if symmetric:
            m0 = f[0] * ub + f[3] * vb + f[6]
            m1 = f[1] * ub + f[4] * vb + f[7]
            w += 0.5 * inv_sqrt(m0 * m0 + m1 * m1)
        d = abs(ub * l0 + vb * l1 + l2) * w
        s = ua + va + ub + vb
        present = s == s
        part += d if present else 0.0
        used += np.int64(present)  # an int64, not a bool, keeps the loop vectorised
    return part, used


#: points per chunk of the float32 block loops. Before each chunk they prefetch the same share
#: of the next pair's blocks (CHUNK x 8 bytes of each): spread over the block's arithmetic,
#: the next blocks stream in from memory while this one is summed. (All of them at the start
#: of a block: no gain, the requests queue up and the arithmetic waits behind them.) On a
#: large-load frame set (2-core Xeon VM, slow memory), alternating runs: full level 16.3-16.9
#: -> 14.7-15.5 ms, 1/8 screen 3.9 -> 3.6 ms (the README's figures); chunks of 128 the same,
#: of 512 about half the gain
CHUNK = 256


#: fewest points per detection for which the block loops prefetch the next pair's blocks: a
#: coarser screen's gathered points stay in cache (on a large-load frame set the 1/32 screen's
#: 576 points per detection are 1.8 MB in all), and its chunked loop cost 0.4 ms more
FETCH_MIN_POINTS = 2048


@inline
def prefetch_share(address, k0, k1):
    """Prefetch towards L2 points k0:k1 of the float32 (u, v) points (8 bytes each) at
    address (0: none)."""
    if address != 0:
        for offset in range(8 * k0, 8 * k1, 64):
            prefetch_l2(address + offset)


@inline
def chunk_step(fetch, m):
    """Points per chunk of a block loop over m points: CHUNK when fetching, else all."""
    return CHUNK if fetch else max(m, 1)


@inline
def chunk_start(k0, m, step, next_a, next_b):
    """End of the chunk from point k0, after prefetching its share at next_a and next_b."""
    k1 = min(k0 + step, m)
    prefetch_share(next_a, k0, k1)
    prefetch_share(next_b, k0, k1)
    return k1


@inline32
def chunk32(a, b, g0, g1, g2, g3, g4, g5, g6, g7, g8, symmetric):
    """block32's three sums over the points of a, b (float32; block32 documents the terms)."""
    p = s = q = np.float32(0.0)
    # a range from 0: the compiler sees non-negative indices (no wraparound: vector loads)
    for k in range(a.shape[0] // 2):
        ua = a[2 * k]
        va = a[2 * k + 1]
        ub = b[2 * k]
        vb = b[2 * k + 1]
        l0 = g0 * ua + g1 * va + g2
        l1 = g3 * ua + g4 * va + g5
        l2 = g6 * ua + g7 * va + g8
        e = abs(ub * l0 + vb * l1 + l2)
        w = np.float32(1.0) / np.sqrt(l0 * l0 + l1 * l1)
        if symmetric:
            m0 = g0 * ub + g3 * vb + g6
            m1 = g1 * ub + g4 * vb + g7
            w += np.float32(1.0) / np.sqrt(m0 * m0 + m1 * m1)
        ew = e * w
        p += ew
        s += w
        q += ew * w
    return p, s, q


@inline32
def block32_sums(a, b, gs, k, symmetric, fetch, next_a, next_b):
    """float32 sums over a block of complete points a, b of a pair under g = gs[k] (9,), its
    camera pair's F in float32: (sum |e| w, sum w, sum |e| w^2) with e = x_b^T g x_a and
    w = wa + wb (symmetric) or wa, wa = 1/||(g x_a)_12||, wb = 1/||(g^T x_b)_12||. fetch: summed in
    chunks of CHUNK points, meanwhile prefetching the same-sized blocks at addresses next_a,
    next_b (0: none); the sums depend on fetch, never on the addresses. Arrays and indices,
    not rows: a row view per call costs reference counting. Inlined into block32 and
    block32_refined, which choose the 1/sqrt."""
    g0, g1, g2, g3, g4 = gs[k, 0], gs[k, 1], gs[k, 2], gs[k, 3], gs[k, 4]
    g5, g6, g7, g8 = gs[k, 5], gs[k, 6], gs[k, 7], gs[k, 8]
    p = s = q = np.float32(0.0)
    m = a.shape[0] // 2
    step = chunk_step(fetch, m)
    for k0 in range(0, m, step):
        k1 = chunk_start(k0, m, step, next_a, next_b)
        ak = a[2 * k0 : 2 * k1]
        bk = b[2 * k0 : 2 * k1]
        # a constant per call: a loop without the branch
        if symmetric:
            dp, ds, dq = chunk32(ak, bk, g0, g1, g2, g3, g4, g5, g6, g7, g8, True)
        else:
            dp, ds, dq = chunk32(ak, bk, g0, g1, g2, g3, g4, g5, g6, g7, g8, False)
        p += dp
        s += ds
        q += dq
    return np.float64(p), np.float64(s), np.float64(q)


@jit32
def block32(a, b, gs, k, symmetric, fetch, next_a, next_b):
    """block32_sums with the 1/sqrt as the hardware estimate (_ESTIMATE)."""
    wide_vectors()
    estimated_rsqrt()
    return block32_sums(a, b, gs, k, symmetric, fetch, next_a, next_b)


@jit32
def block32_refined(a, b, gs, k, symmetric):
    """block32_sums with LLVM's refined 1/sqrt (the estimate and its Newton steps, within
    epipolar.RSQRT_ERR_REFINED): the second try of a pair the estimate's bound cannot
    settle."""
    wide_vectors()
    return block32_sums(a, b, gs, k, symmetric, False, 0, 0)


@jit32
def b_terms(ub, vb, l0, l1, l2, wa, g0, g1, g3, g4, g6, g7, symmetric):
    """(|e| w, w) of one point of a pair: b point (ub, vb), the line (l0, l1, l2) of its a
    point and that line's weight wa, g0..g8 the pair's F in float32."""
    e = abs(ub * l0 + vb * l1 + l2)
    m0 = g0 * ub + g3 * vb + g6
    m1 = g1 * ub + g4 * vb + g7
    wb = np.float32(1.0) / np.sqrt(m0 * m0 + m1 * m1)
    w = wa + wb if symmetric else wa  # the select keeps the loop branch-free
    return e * w, w


@inline32
def chunk32x2(a, b, d, g0, g1, g2, g3, g4, g5, g6, g7, g8, symmetric):
    """block32x2's six sums over the points of a, b, d."""
    p1 = s1 = q1 = p2 = s2 = q2 = np.float32(0.0)
    for j in range(a.shape[0] // 2):
        ua = a[2 * j]
        va = a[2 * j + 1]
        l0 = g0 * ua + g1 * va + g2
        l1 = g3 * ua + g4 * va + g5
        l2 = g6 * ua + g7 * va + g8
        wa = np.float32(1.0) / np.sqrt(l0 * l0 + l1 * l1)
        ew, w = b_terms(b[2 * j], b[2 * j + 1], l0, l1, l2, wa, g0, g1, g3, g4, g6, g7, symmetric)
        p1 += ew
        s1 += w
        q1 += ew * w
        ew, w = b_terms(d[2 * j], d[2 * j + 1], l0, l1, l2, wa, g0, g1, g3, g4, g6, g7, symmetric)
        p2 += ew
        s2 += w
        q2 += ew * w
    return p1, s1, q1, p2, s2, q2


@jit32
def block32x2(a, b, d, gs, k, symmetric, fetch, next_a, next_b):
    """block32 of two pairs of one camera pair (F gs[k]) that share a's detection, (a, b)
    and (a, d): a's lines and weights computed once; returns block32's three sums for each
    pair (fetch, next_a, next_b as in block32)."""
    wide_vectors()
    estimated_rsqrt()
    g0, g1, g2, g3, g4 = gs[k, 0], gs[k, 1], gs[k, 2], gs[k, 3], gs[k, 4]
    g5, g6, g7, g8 = gs[k, 5], gs[k, 6], gs[k, 7], gs[k, 8]
    p1 = s1 = q1 = p2 = s2 = q2 = np.float32(0.0)
    m = a.shape[0] // 2
    step = chunk_step(fetch, m)
    for k0 in range(0, m, step):
        k1 = chunk_start(k0, m, step, next_a, next_b)
        ak = a[2 * k0 : 2 * k1]
        bk = b[2 * k0 : 2 * k1]
        dk = d[2 * k0 : 2 * k1]
        if symmetric:
            dp1, ds1, dq1, dp2, ds2, dq2 = chunk32x2(ak, bk, dk, g0, g1, g2, g3, g4, g5, g6, g7, g8, True)
        else:
            dp1, ds1, dq1, dp2, ds2, dq2 = chunk32x2(ak, bk, dk, g0, g1, g2, g3, g4, g5, g6, g7, g8, False)
        p1 += dp1
        s1 += ds1
        q1 += dq1
        p2 += dp2
        s2 += ds2
        q2 += dq2
    return (
        (np.float64(p1), np.float64(s1), np.float64(q1)),
        (np.float64(p2), np.float64(s2), np.float64(q2)),
    )


@plain
def float32_f(fs):
    """(g (W, 9) float32, G (W, 3, 3) float64 = |g|): the unit F of each camera pair (fs
    (W, 9) row-major) rounded to float32, the float32 kernels' F (EPIPOLE_NORM applies in its
    units as it is; the error bound does not depend on its scale)."""
    W = fs.shape[0]
    g = np.empty((W, 9), dtype=np.float32)
    G = np.empty((W, 3, 3))
    for k in range(W):
        for e in range(9):
            g[k, e] = np.float32(fs[k, e])
            G[k, e // 3, e % 3] = abs(np.float64(g[k, e]))
    return g, G


@inline
def block_bound(G, t, epi, xa0, xa1, xb0, xb1, sums, h, m, rsqrt_err):
    """(float32 block sum, upper bound (px) on its distance to the exact sum) of a pair's
    block of m points (G[t] = |g|, g its camera pair's float32 F); xa0, xa1, xb0, xb1 bound
    |u|, |v| of the points in a and b (module docstring); epi: EPIPOLE_NORM in g's units;
    h = 0.5 (symmetric) or 1; rsqrt_err: relative error bound of the sums' 1/sqrt. (inf,
    inf) when the block must be summed in float64."""
    # rows of G times (xa0, xa1, 1), then xb's weights: no loops, no tuple indexing (this
    # runs per pair and block)
    r0 = G[t, 0, 0] * xa0 + G[t, 0, 1] * xa1 + G[t, 0, 2]
    r1 = G[t, 1, 0] * xa0 + G[t, 1, 1] * xa1 + G[t, 1, 2]
    r2 = G[t, 2, 0] * xa0 + G[t, 2, 1] * xa1 + G[t, 2, 2]
    bil = r0 * xb0 + r1 * xb1 + r2
    la = r0 + r1
    lb = (G[t, 0, 0] + G[t, 0, 1]) * xb0 + (G[t, 1, 0] + G[t, 1, 1]) * xb1 + G[t, 2, 0] + G[t, 2, 1]
    lmax = max(la, lb) if h != 1.0 else la
    p, s, q = sums
    # a point at the epipole (float64 rule: ||l_12|| <= EPIPOLE_NORM = epi in g's units)
    # has a float32 line norm within the rounding bound 6 u L of that: its weight, and so
    # the block's weight sum, reaches 1 / (epi + 6 u L); such a block goes to float64
    # (part inf)
    if not s * (epi + 6.0 * U32 * lmax) * (1.0 + 2.0 * rsqrt_err) < 1.0:
        return np.inf, np.inf
    part = h * p
    # sum |e| (wa^2 + wb^2) <= sum |e| w^2 bounds the line-norm term of both sides
    err = 10.0 * U32 * bil * h * s + 8.0 * U32 * h * lmax * q + (rsqrt_err + (m + 8) * U32) * part
    return part, err * (1.0 + BOUND_SLACK)


@plain
def pair64(a, b, fs, fk, blocks, n, tau, early_exit, ha, symmetric):
    """(sum, used, index of the last block summed) of one pair in float64, blocks in order,
    exact early exit."""
    total = 0.0
    count = 0
    seen = 0
    last = blocks.shape[0] - 1
    for r in range(blocks.shape[0]):
        lo = blocks[r, 0]
        hi = blocks[r, 1]
        p, c = block64(a[2 * lo : 2 * hi], b[2 * lo : 2 * hi], fs, fk, ha, symmetric)
        total += p if p == p else np.inf  # NaN: undefined line -> cannot pass
        count += c
        seen += hi - lo
        # count + points still to come bounds the final count from above
        if early_exit and total >= tau * (count + (n - seen)):
            last = r
            break
    return total, count, last


@inline
def pair64_into(
    s, like, det_addr, pa, pb, fs, fk, blocks, n, tau, early_exit, h, symmetric, sums, used, last
):
    """pair64 of pair s (detections pa[s], pb[s] under fs[fk[s]]) into sums, used, last."""
    sums[s], used[s], last[s] = pair64(
        points(like, det_addr[pa[s]], 0, 2 * n),
        points(like, det_addr[pb[s]], 0, 2 * n),
        fs,
        fk[s],
        blocks,
        n,
        tau,
        early_exit,
        h,
        symmetric,
    )


@plain
def present64(a, b):
    """Points of a block that both detections have: block64's test (the float64 sum of the
    four coordinates is not NaN), without the distances."""
    count = 0
    for k in range(a.shape[0] // 2):
        s = np.float64(a[2 * k]) + np.float64(a[2 * k + 1]) + np.float64(b[2 * k]) + np.float64(b[2 * k + 1])
        count += np.int64(s == s)
    return count


@plain
def rest_present(a, b, blocks, after):
    """Points of the blocks after block index ``after`` that both a and b (2n,) have."""
    count = 0
    for r in range(after + 1, blocks.shape[0]):
        lo = blocks[r, 0]
        hi = blocks[r, 1]
        count += present64(a[2 * lo : 2 * hi], b[2 * lo : 2 * hi])
    return count


@inline
def pair_bound(G, k, ranges, i, j, r, sums3, h, m, rsqrt_err=RSQRT_ERR):
    """block_bound of a pair (detections i, j, camera pair k) from their block r's (m points)
    coordinate ranges ranges[i, r], ranges[j, r] (min, max over u and v); rsqrt_err: that of
    the sums (block32's by default)."""
    xa = max(abs(ranges[i, r, 0]), abs(ranges[i, r, 1]))
    xb = max(abs(ranges[j, r, 0]), abs(ranges[j, r, 1]))
    return block_bound(G, k, EPIPOLE_NORM, xa, xa, xb, xb, sums3, h, m, rsqrt_err)


@inline
def settle(s, p, e, m, rest, tau, early_exit, sums, err, used, alive):
    """Add pair s's block: its float32 sum p within e, over m points; then the exact early
    exit, ``rest`` points still to come (alive[s] False; the block loop notes the block).
    Only scalars and the result arrays: the float64 case is settle64, a call the caller
    makes (an array passed on to a call from inlined code costs the loop reference counting
    on every pair, ~45 ns: the large load's 1/32 screen took 2.25 instead of 2.0 ms)."""
    sums[s] += p
    err[s] += e
    used[s] += m
    exit_early(s, rest, tau, early_exit, sums, err, used, alive)


@plain
def settle64(s, ab, bb, fs, fk, rest, h, symmetric, tau, early_exit, sums, err, used, alive):
    """Add pair s's block summed in float64 (blocks ab, bb under fs[fk]): where the float32
    bound is inf (a missing point, a point at or very near the epipole); then the exact
    early exit as in settle."""
    p, k = block64(ab, bb, fs, fk, h, symmetric)
    sums[s] += p if p == p else np.inf
    used[s] += k
    exit_early(s, rest, tau, early_exit, sums, err, used, alive)


@inline
def exit_early(s, rest, tau, early_exit, sums, err, used, alive):
    """alive[s] False once pair s cannot pass: exact, sum - err is below the exact partial
    sum, and ``rest`` points are still to come."""
    if early_exit and sums[s] - err[s] >= tau * (used[s] + rest):
        alive[s] = False


@inline
def next_blocks(t, pa, pb, det_addr, offset, fetch):
    """Addresses of the points at byte ``offset`` of pair t + 1's detections in a and b (the
    blocks the kernel reads next); 0 where fetch is off, there is no next pair or pair t
    reads the same detection."""
    u = t + 1
    if u >= pa.shape[0] or not fetch:
        return 0, 0
    next_a = det_addr[pa[u]] + offset if pa[u] != pa[t] else 0
    next_b = det_addr[pb[u]] + offset if pb[u] != pb[t] else 0
    return next_a, next_b


@inline
def pair_block(s, r, lo, hi, like, det_addr, pa, pb, ranges):
    """Block r = points lo:hi of pair s: its detections i, j, their points there and whether
    every one of those coordinates is finite (block_range, cached in ranges)."""
    i = pa[s]
    j = pb[s]
    ab = points(like, det_addr[i], 2 * lo, 2 * (hi - lo))
    bb = points(like, det_addr[j], 2 * lo, 2 * (hi - lo))
    lo_a, hi_a = block_range(ab, ranges, i, r)
    lo_b, hi_b = block_range(bb, ranges, j, r)
    return i, j, ab, bb, lo_a <= hi_a and lo_b <= hi_b


@inline
def single(
    s,
    r,
    lo,
    hi,
    rest,
    like,
    det_addr,
    pa,
    pb,
    ranges,
    g,
    G,
    fs,
    fk,
    h,
    symmetric,
    tau,
    early_exit,
    sums,
    err,
    used,
    alive,
    fetch,
):
    """Block r = points lo:hi of pair s alone (fetch: in chunks, prefetching the next pair's
    blocks)."""
    i, j, ab, bb, finite = pair_block(s, r, lo, hi, like, det_addr, pa, pb, ranges)
    p = np.inf
    e = np.inf
    if finite:  # no NaN or inf coordinate
        next_a, next_b = next_blocks(s, pa, pb, det_addr, 2 * lo * like.itemsize, fetch)
        p, e = pair_bound(
            G, fk[s], ranges, i, j, r, block32(ab, bb, g, fk[s], symmetric, fetch, next_a, next_b), h, hi - lo
        )
    if p < np.inf and e < np.inf:
        settle(s, p, e, hi - lo, rest, tau, early_exit, sums, err, used, alive)
    else:
        settle64(s, ab, bb, fs, fk[s], rest, h, symmetric, tau, early_exit, sums, err, used, alive)


@inline
def decided(total, bound, count, tau):
    """Whether a complete sum within ``bound`` of the exact one settles the decision
    (exact sum < tau * count)."""
    return total + bound < tau * count or total - bound >= tau * count


@plain
def centred(x, n):
    """(float32 copy of the 2n coordinates x with the integer px (c0, c1) near them
    subtracted, c0, c1): the points of a detection centred on its first complete point
    (0, 0 if none), so the float32 bilinear form's rounding scales with the detection's
    extent, not with its distance from the image origin."""
    c0 = c1 = 0.0
    for k in range(n):
        if x[2 * k] == x[2 * k] and x[2 * k + 1] == x[2 * k + 1]:
            c0 = np.floor(np.float64(x[2 * k]) + 0.5)
            c1 = np.floor(np.float64(x[2 * k + 1]) + 0.5)
            break
    out = np.empty(2 * n, dtype=np.float32)
    for k in range(n):
        out[2 * k] = x[2 * k] - np.float32(c0)
        out[2 * k + 1] = x[2 * k + 1] - np.float32(c1)
    return out, c0, c1


@plain
def centred_f(f, ca0, ca1, cb0, cb1):
    """(g (1, 9) float32, G (1, 3, 3) = |g|): g = T_b^T F T_a, the unit F (f (9,) row-major)
    of points centred on (ca0, ca1) in a and (cb0, cb1) in b ((g x)_12 = (F x)_12, so
    EPIPOLE_NORM applies in g's units as it is)."""
    h02 = f[0] * ca0 + f[1] * ca1 + f[2]
    h12 = f[3] * ca0 + f[4] * ca1 + f[5]
    h22 = f[6] * ca0 + f[7] * ca1 + f[8]
    t = np.array(
        [
            f[0],
            f[1],
            h02,
            f[3],
            f[4],
            h12,
            cb0 * f[0] + cb1 * f[3] + f[6],
            cb0 * f[1] + cb1 * f[4] + f[7],
            cb0 * h02 + cb1 * h12 + h22,
        ]
    )
    return float32_f(t.reshape(1, 9))


@inline
def refined_pair(s, like, det_addr, pa, pb, blocks, n, fs, fk, h, symmetric):
    """(sum, its error bound, points used) of pair s over all its blocks with block32_refined
    on its points centred on each detection, under its centred F: the bound's rounding terms
    scale with the detections' extent, not with their distance from the image origin (blocks
    with a missing point or a point near the epipole in float64, as in settle)."""
    a = points(like, det_addr[pa[s]], 0, 2 * n)
    b = points(like, det_addr[pb[s]], 0, 2 * n)
    ac, ca0, ca1 = centred(a, n)
    bc, cb0, cb1 = centred(b, n)
    g, G = centred_f(fs[fk[s]], ca0, ca1, cb0, cb1)
    ranges = np.full((2, blocks.shape[0], 2), np.nan)
    total = 0.0
    bound = 0.0
    count = 0
    for r in range(blocks.shape[0]):
        lo = blocks[r, 0]
        hi = blocks[r, 1]
        ab = ac[2 * lo : 2 * hi]
        bb = bc[2 * lo : 2 * hi]
        lo_a, hi_a = block_range(ab, ranges, 0, r)
        lo_b, hi_b = block_range(bb, ranges, 1, r)
        p = np.inf
        e = np.inf
        if lo_a <= hi_a and lo_b <= hi_b:
            p, e = pair_bound(
                G, 0, ranges, 0, 1, r, block32_refined(ab, bb, g, 0, symmetric), h, hi - lo, RSQRT_ERR_REFINED
            )
        if p < np.inf and e < np.inf:
            total += p
            bound += e
            count += hi - lo
        else:
            p, k = block64(a[2 * lo : 2 * hi], b[2 * lo : 2 * hi], fs, fk[s], h, symmetric)
            total += p if p == p else np.inf
            count += k
    return total, bound, count
