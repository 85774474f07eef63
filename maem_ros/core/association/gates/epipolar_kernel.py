"""The numba kernels of the epipolar gate (core.association.gates.epipolar; imported only
when numba is installed): every pair of a frame in one call (sums_kernel: blocks outermost,
pairs in a cache-friendly order), the gathers of a subset read in runs, the preparing pass's
scan (block ranges) and copies, and the float32 1/sqrt probes.

Every kernel is a module-level function so numba's on-disk cache (``cache=True``) finds it again
in a new process: a kernel defined in a closure is hashed with the closure's compiled callees,
whose identity changes from process to process, so each process recompiled them and added new
cache files. The per-block arithmetic is epipolar_blocks'.
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.association.gates.epipolar_blocks import (
    FETCH_MIN_POINTS,
    block32x2,
    decided,
    float32_f,
    next_blocks,
    pair64_into,
    pair_bound,
    refined_pair,
    rest_present,
    settle,
    settle64,
    single,
)
from maem_ros.core.association.gates.epipolar_jit import (
    estimated_rsqrt,
    inline,
    inline32,
    jit32,
    plain,
    points,
    prefetch,
    wide_vectors,
)
from maem_ros.core.association.gates.epipolar_ranges import block_range, key_range, key_values


@plain
def sums_kernel(
    like, det_addr, ranges, fs, fk, pa, pb, blocks, n, tau, early_exit, symmetric, mixed, refine, count_rest
):
    """(sums, used, points summed) of pairs s (detections pa[s], pb[s] under unit F
    fs[fk[s]]); detection d's 2n coordinates start at address det_addr[d] (arrays of like's
    dtype); ranges (D, blocks, 2) float64: each detection's block ranges (block_range; NaN:
    not known yet, filled on first use). count_rest: used also counts the points after a
    rejected pair's early exit.
    mixed: float32 sums with the estimated 1/sqrt (block32); a pair their bound cannot
    settle is summed again with the refined 1/sqrt (refine) and, if that cannot settle it
    either, in float64.
    Pairs of one detection in one camera pair (runs, consecutive in the given order) are
    summed together; with several blocks the runs are taken in locality_order (each pair's
    sums are those of the given order: they depend on its run, not on the runs' order)."""
    if not (mixed and blocks.shape[0] > 1):
        return ordered_sums(
            like,
            det_addr,
            ranges,
            fs,
            fk,
            pa,
            pb,
            blocks,
            n,
            tau,
            early_exit,
            symmetric,
            mixed,
            refine,
            count_rest,
        )
    perm = locality_order(pa, pb, fk, ranges.shape[0], LOCALITY_BLOCKS)
    got = ordered_sums(
        like,
        det_addr,
        ranges,
        fs,
        fk[perm],
        pa[perm],
        pb[perm],
        blocks,
        n,
        tau,
        early_exit,
        symmetric,
        mixed,
        refine,
        count_rest,
    )
    sums = np.empty(perm.size)
    total = np.empty(perm.size, dtype=np.int64)
    used = np.empty(perm.size, dtype=np.int64)
    sums[perm] = got[0]
    total[perm] = got[1]
    used[perm] = got[2]
    return sums, total, used


#: detection blocks the pair order of locality_order assumes stay in cache: BLOCK points of
#: float32 (u, v) are 32 KB, so 48 fill 1.5 MB of a 2 MB L2, the rest left to the kernel's
#: other reads. On a large-load frame set's full-mesh level (814 pairs of 386 detections,
#: one connected graph of degree ~4), counted in an LRU cache of 48 blocks: 937 block loads a
#: round in the detection order, 720 in locality_order's, and the level is faster by a few
#: percent in alternating runs (24, 96 or 192: within noise of 48). The screens (one block
#: each, their points in cache) gained nothing: not reordered
LOCALITY_BLOCKS = 48


@plain
def locality_order(pa, pb, fk, D, cap):
    """A permutation of the pairs (pa[s], pb[s] detections < D, fk[s] camera pair) that
    keeps each run (consecutive pairs of one pa and fk) whole and in order, and orders the
    runs so that the detections they read are read again soon: greedily, the next run is one
    of the most recently read detection that has runs left (the one reading most
    detections still among the last ``cap`` read), else the first of the detection with
    the most runs left. The blocks outermost loop reads each detection's block once per
    pair; this order lets more of those reads hit the cache."""
    S = pa.shape[0]
    start = np.empty(S + 1, dtype=np.int64)
    R = 0
    for s in range(S):
        if s == 0 or pa[s] != pa[s - 1] or fk[s] != fk[s - 1]:
            start[R] = s
            R += 1
    start[R] = S
    # incidence of detections and runs (CSR): a run's a side once, each of its b sides
    count = np.zeros(D + 1, dtype=np.int64)
    for r in range(R):
        count[pa[start[r]] + 1] += 1
        for s in range(start[r], start[r + 1]):
            count[pb[s] + 1] += 1
    for d in range(D):
        count[d + 1] += count[d]
    runs_of = np.empty(count[D], dtype=np.int64)
    fill = count[:D].copy()
    for r in range(R):
        d = pa[start[r]]
        runs_of[fill[d]] = r
        fill[d] += 1
        for s in range(start[r], start[r + 1]):
            runs_of[fill[pb[s]]] = r
            fill[pb[s]] += 1
    left = count[1:] - count[:D]
    done = np.zeros(R, dtype=np.bool_)
    cached = np.zeros(D, dtype=np.bool_)
    recent = np.full(cap, -1, dtype=np.int64)  # the last cap detections read, oldest first
    perm = np.empty(S, dtype=np.int64)
    at = 0
    for _ in range(R):
        pick = -1
        for slot in range(cap - 1, -1, -1):
            d = recent[slot]
            if d < 0:
                break
            best = -1
            for x in range(count[d], count[d + 1]):
                r = runs_of[x]
                if done[r]:
                    continue
                hits = np.int64(cached[pa[start[r]]])
                for s in range(start[r], start[r + 1]):
                    hits += cached[pb[s]]
                if hits > best:
                    best = hits
                    pick = r
            if pick >= 0:
                break
        if pick < 0:
            d = np.argmax(left)
            for x in range(count[d], count[d + 1]):
                if not done[runs_of[x]]:
                    pick = runs_of[x]
                    break
        done[pick] = True
        read_recently(pa[start[pick]], left, cached, recent)
        for s in range(start[pick], start[pick + 1]):
            perm[at] = s
            at += 1
            read_recently(pb[s], left, cached, recent)
    return perm


@inline
def read_recently(d, left, cached, recent):
    """Detection d read by a run: one run fewer left for it, and it the most recent of the
    cache ``recent`` (oldest first, -1 = empty; on a miss the oldest drops out)."""
    left[d] -= 1
    slot = 0
    if cached[d]:
        while recent[slot] != d:
            slot += 1
    elif recent[0] >= 0:
        cached[recent[0]] = False
    for k in range(slot, recent.shape[0] - 1):
        recent[k] = recent[k + 1]
    recent[recent.shape[0] - 1] = d
    cached[d] = True


# fmt: off
# (the frame kernel's hot loop keeps its dense layout: formatted, its calls of 10-16
# arguments would take one line each and the loop would no longer read as one screen)
@plain
def ordered_sums(like, det_addr, ranges, fs, fk, pa, pb, blocks, n, tau, early_exit,
                 symmetric, mixed, refine, count_rest):
    """sums_kernel of the pairs in the order given."""
    S = pa.shape[0]
    h = 0.5 if symmetric else 1.0
    # n alone decides the chunking, so a pair's sums do not depend on the other pairs
    fetch = n >= FETCH_MIN_POINTS
    sums = np.zeros(S)
    used = np.zeros(S, dtype=np.int64)
    # the last block each pair summed (early exit); -1: still summing
    last = np.full(S, -1, dtype=np.int64)
    if not mixed:
        for s in range(S):
            pair64_into(s, like, det_addr, pa, pb, fs, fk, blocks, n, tau, early_exit, h,
                        symmetric, sums, used, last)
        return _with_rest(like, det_addr, pa, pb, blocks, n, sums, used, last, count_rest)
    # each camera pair's float32 F, then the blocks outermost: one block of every detection
    # stays in cache while all its candidate pairs read it; a run's lines and weights in a
    # are computed once, two pairs at a time
    g, G = float32_f(fs)
    run_end = run_ends(pa, fk)
    err = np.zeros(S)
    alive = np.ones(S, dtype=np.bool_)  # not rejected early
    seen = 0
    for r in range(blocks.shape[0]):
        lo, hi = blocks[r, 0], blocks[r, 1]
        seen += hi - lo
        s = 0
        while s < S:
            first = -1  # an alive pair of the run waiting for a second one
            for t in range(s, run_end[s]):
                if not alive[t]:
                    continue
                if first < 0:
                    first = t
                    continue
                i, j, j2 = pa[t], pb[first], pb[t]
                ab = points(like, det_addr[i], 2 * lo, 2 * (hi - lo))
                bb = points(like, det_addr[j], 2 * lo, 2 * (hi - lo))
                db = points(like, det_addr[j2], 2 * lo, 2 * (hi - lo))
                lo_a, hi_a = block_range(ab, ranges, i, r)
                lo_b, hi_b = block_range(bb, ranges, j, r)
                lo_d, hi_d = block_range(db, ranges, j2, r)
                if lo_a <= hi_a and lo_b <= hi_b and lo_d <= hi_d:
                    next_a, next_b = next_blocks(t, pa, pb, det_addr,
                                                 2 * lo * like.itemsize, fetch)
                    one, two = block32x2(ab, bb, db, g, fk[t], symmetric, fetch, next_a,
                                         next_b)
                    p, e = pair_bound(G, fk[t], ranges, i, j, r, one, h, hi - lo)
                    if p < np.inf and e < np.inf:
                        settle(first, p, e, hi - lo, n - seen, tau, early_exit, sums, err,
                               used, alive)
                    else:
                        settle64(first, ab, bb, fs, fk[first], n - seen, h, symmetric, tau,
                                 early_exit, sums, err, used, alive)
                    p, e = pair_bound(G, fk[t], ranges, i, j2, r, two, h, hi - lo)
                    if p < np.inf and e < np.inf:
                        settle(t, p, e, hi - lo, n - seen, tau, early_exit, sums, err, used,
                               alive)
                    else:
                        settle64(t, ab, db, fs, fk[t], n - seen, h, symmetric, tau,
                                 early_exit, sums, err, used, alive)
                else:
                    for u in (first, t):
                        single(u, r, lo, hi, n - seen, like, det_addr, pa, pb, ranges, g, G,
                               fs, fk, h, symmetric, tau, early_exit, sums, err, used, alive,
                               fetch)
                first = -1
            if first >= 0:
                single(first, r, lo, hi, n - seen, like, det_addr, pa, pb, ranges,
                       g, G, fs, fk, h, symmetric, tau, early_exit, sums, err,
                       used, alive, fetch)
            s = run_end[s]
        for t in range(S):  # where this block's early exits stopped
            if not alive[t] and last[t] < 0:
                last[t] = r
    settle_open(like, det_addr, pa, pb, blocks, n, fs, fk, h, symmetric, tau, early_exit,
                refine, sums, err, used, alive, last)
    return _with_rest(like, det_addr, pa, pb, blocks, n, sums, used, last, count_rest)
# fmt: on


@inline
def run_ends(pa, fk):
    """run_end[s]: the end of pair s's run (the pairs of its a-side detection in its camera
    pair, consecutive)."""
    S = pa.shape[0]
    run_end = np.empty(S, dtype=np.int64)
    for s in range(S - 1, -1, -1):
        same = s + 1 < S and pa[s + 1] == pa[s] and fk[s + 1] == fk[s]
        run_end[s] = run_end[s + 1] if same else s + 1
    return run_end


@inline
def settle_open(
    like,
    det_addr,
    pa,
    pb,
    blocks,
    n,
    fs,
    fk,
    h,
    symmetric,
    tau,
    early_exit,
    refine,
    sums,
    err,
    used,
    alive,
    last,
):
    """The alive pairs whose float32 bound does not settle the decision (the mean is within
    ~2^-10 of tau): again with the refined 1/sqrt (~2^-20), then float64 throughout."""
    for s in range(pa.shape[0]):
        if not alive[s] or decided(sums[s], err[s], used[s], tau):
            continue
        if refine:
            total, bound, count = refined_pair(s, like, det_addr, pa, pb, blocks, n, fs, fk, h, symmetric)
            if decided(total, bound, count, tau):
                sums[s] = total
                used[s] = count
                continue
        pair64_into(
            s, like, det_addr, pa, pb, fs, fk, blocks, n, tau, early_exit, h, symmetric, sums, used, last
        )


@plain
def _with_rest(like, det_addr, pa, pb, blocks, n, sums, used, last, count_rest):
    """(sums, used with the points after each early exit when count_rest, points summed)."""
    total = used.copy()
    if count_rest:
        for s in range(used.shape[0]):
            if 0 <= last[s] < blocks.shape[0] - 1:
                total[s] += rest_present(
                    points(like, det_addr[pa[s]], 0, 2 * n),
                    points(like, det_addr[pb[s]], 0, 2 * n),
                    blocks,
                    last[s],
                )
    return sums, total, used


#: runs prefetched ahead of the one gather_runs copies: the runs are separate cache lines
#: (one every period points) that the hardware prefetchers do not follow across pages, so
#: without the hint the copy waits for memory one line at a time (8 ahead: about a third
#: less time for a large-load screen from cold memory; 16 or 32: no better)
_RUNS_AHEAD = 8


@plain
def gather_runs(like, det_addr, run, period, out, every, coarse):
    """out[d] (2n,) = the n points of the detection at address det_addr[d] read in runs of
    ``run`` consecutive points, one run every ``period`` points (PointRows.run/period); and
    (every > 0) coarse[d] = every ``every``-th of those runs, as long as coarse has room: a
    coarser subset copied in the same pass."""
    wide_vectors()
    runs = out.shape[1] // (2 * run)
    D = det_addr.shape[0]
    for d in range(D):
        for r in range(runs):
            ahead = r + _RUNS_AHEAD  # this detection's later run, else the next one's first
            if ahead < runs:
                prefetch(det_addr[d] + 2 * ahead * period * like.itemsize)
            elif d + 1 < D:
                prefetch(det_addr[d + 1] + 2 * (ahead - runs) * period * like.itemsize)
            copy_run(points(like, det_addr[d], 2 * r * period, 2 * run), d, r, out, every, coarse)


@inline
def copy_run(src, d, r, out, every, coarse):
    """Run r of detection d (src: its 2 * run coordinates) into out[d] and, when it is one
    of every ``every``-th runs and coarse has room, into coarse[d] (gather_runs)."""
    width = src.shape[0]
    for k in range(width):
        out[d, r * width + k] = src[k]
    if every > 0 and r % every == 0 and (r // every + 1) * width <= coarse.shape[1]:
        for k in range(width):
            coarse[d, (r // every) * width + k] = src[k]


#: float32 bits without the sign, and those of inf
_ABS_BITS = np.uint32(0x7FFFFFFF)
_INF_BITS = np.uint32(0x7F800000)


@plain
def scan_gather_runs(
    like, det_addr, n, block, run, period, out, every, coarse, ranges, out_ranges, coarse_ranges
):
    """gather_runs of detections of n float32 points each, each detection's ranges[d, b]
    (float32) = block_range of its points b * block:(b + 1) * block (the kernel's blocks in
    their natural order), out_ranges and coarse_ranges the same of its rows of out and
    coarse (copies: float32, C-contiguous), and the first detection d with an infinite
    coordinate (-1: none; NaN is not inf). Each detection is scanned whole, then its runs
    copied while it is still in cache: one pass from memory, the one a finiteness check
    makes anyway, instead of a second one over scattered cache lines."""
    wide_vectors()
    runs = out.shape[1] // (2 * run)
    first_inf = -1
    for d in range(det_addr.shape[0]):
        address_ranges(like, det_addr[d], n, block, ranges, d)
        for b in range(ranges.shape[1]):
            # a NaN or inf in the block: whether an inf (the finiteness check)
            if (
                first_inf < 0
                and not ranges[d, b, 0] <= ranges[d, b, 1]
                and has_inf(block_points(like, det_addr[d], n, block, b).view(np.uint32))
            ):
                first_inf = d
        for r in range(runs):
            copy_run(points(like, det_addr[d], 2 * r * period, 2 * run), d, r, out, every, coarse)
        # the copies' rows, just written (in cache)
        address_ranges(out, out.ctypes.data + d * out.strides[0], out.shape[1] // 2, block, out_ranges, d)
        if every > 0:
            address_ranges(
                coarse,
                coarse.ctypes.data + d * coarse.strides[0],
                coarse.shape[1] // 2,
                block,
                coarse_ranges,
                d,
            )
    return first_inf


@inline
def block_points(like, address, n, block, b):
    """Points b * block:(b + 1) * block (2 coordinates each) of the n float32 points at
    address."""
    start = b * block
    return points(like, address, 2 * start, 2 * (min(start + block, n) - start))


@inline
def address_ranges(like, address, n, block, ranges, d):
    """ranges[d, b] = block_range of each block b of the n float32 points at address."""
    for b in range(ranges.shape[1]):
        lo, hi = key_range(block_points(like, address, n, block, b).view(np.int32))
        ranges[d, b, 0], ranges[d, b, 1] = key_values(lo, hi)


@inline
def has_inf(bits):
    """Whether float32 values (their uint32 bits) hold +-inf: an integer min over
    |bits| xor inf's bits, which is 0 only for inf (a min reduction vectorises; an early
    break would not)."""
    least = _INF_BITS
    for k in range(bits.shape[0]):
        least = min(least, (bits[k] & _ABS_BITS) ^ _INF_BITS)
    return least == 0


@inline32
def rsqrt32_chunks(q, out, step):
    """out[k] = 1/sqrt(q[k]) in float32, in chunks of ``step`` arguments (shorter than one
    vector: the loop's remainder code)."""
    n = q.shape[0]
    for start in range(0, n, step):
        qk = q[start : min(start + step, n)]
        ok = out[start : min(start + step, n)]
        for k in range(qk.shape[0]):
            ok[k] = np.float32(1.0) / np.sqrt(qk[k])


@jit32
def rsqrt32(q, out, step):
    """rsqrt32_chunks compiled as block32 is (the probe of rsqrt_check.rsqrt_within_bound)."""
    wide_vectors()
    estimated_rsqrt()
    rsqrt32_chunks(q, out, step)


@jit32
def rsqrt32_refined(q, out, step):
    """rsqrt32_chunks compiled as block32_refined is (the probe of
    rsqrt_check.rsqrt_within_bound)."""
    wide_vectors()
    rsqrt32_chunks(q, out, step)
