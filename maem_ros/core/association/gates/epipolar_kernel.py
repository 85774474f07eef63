"""The numba kernels of core/association/gates/epipolar.py (imported only when numba is installed).

Every kernel is a module-level function so numba's on-disk cache (``cache=True``) finds it again
in a new process: a kernel defined in a closure is hashed with the closure's compiled callees,
whose identity changes from process to process, so each process recompiled them (~10 s per
node start) and added new cache files. The arithmetic, its error bound and the decisions are
documented in core/association/gates/epipolar.py.
"""
from __future__ import annotations

import numba as nb
import numpy as np
from numba.core import cgutils

from maem_ros.core.association.gates.epipolar import (_BOUND_SLACK, _KEY_NEG_INF, _KEY_POS_INF, _RSQRT_ERR,
                       _RSQRT_ERR_REFINED, _U32, EPIPOLE_NORM)

# no nnan/ninf fast-math flags: NaN (missing point) and inf (point at the epipole) must
# survive; error_model numpy removes the ZeroDivisionError branch that blocks SIMD;
# reassoc lets the sums vectorise
_FLAGS = {"reassoc", "contract", "arcp", "nsz"}
_OPTS = dict(cache=True, error_model="numpy", boundscheck=False, nogil=True)
jit = nb.njit(fastmath=_FLAGS, **_OPTS)
# afn: float32 1/sqrt as the hardware estimate (_ESTIMATE; bounded by _RSQRT_ERR)
jit32 = nb.njit(fastmath=_FLAGS | {"afn"}, **_OPTS)
plain = nb.njit(**_OPTS)
# per pair and block helpers: inlined, so the hot loop passes no array views through calls
inline = nb.njit(inline="always", **_OPTS)
inline32 = nb.njit(fastmath=_FLAGS | {"afn"}, inline="always", **_OPTS)


@nb.extending.intrinsic
def pointer_like(typingctx, like, address):
    """The int64 address as a pointer to like's dtype."""
    sig = nb.types.CPointer(like.dtype)(like, address)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[1], context.get_value_type(signature.return_type))
    return sig, codegen


def _prefetch_intrinsic(locality: int, towards: str):
    """An intrinsic asking the CPU to bring the cache line at an int64 address towards
    ``towards`` (a hint: never faults, even for an address outside any mapping); LLVM's
    temporal locality 3 = L1, 2 = L2."""
    @nb.extending.intrinsic
    def intrinsic(typingctx, address):
        sig = nb.types.void(nb.types.int64)

        def codegen(context, builder, signature, args):
            # numba's codegen types (llvmlite, which numba brings): no import of llvmlite here
            byte_ptr = cgutils.voidptr_t
            i32 = cgutils.int32_t
            fn = builder.module.declare_intrinsic(
                "llvm.prefetch", [byte_ptr],
                cgutils.ir.FunctionType(cgutils.ir.VoidType(), [byte_ptr, i32, i32, i32]))
            # read (0), locality, data cache (1)
            builder.call(fn, [builder.inttoptr(args[0], byte_ptr), i32(0), i32(locality),
                              i32(1)])
            return context.get_dummy_value()
        return sig, codegen
    intrinsic.__doc__ = f"Prefetch the cache line at the int64 address towards {towards}."
    return intrinsic


prefetch = _prefetch_intrinsic(3, "L1")
prefetch_l2 = _prefetch_intrinsic(2, "L2")


#: LLVM function attribute: vectorise with 512-bit registers where the CPU has them. LLVM's
#: tuning for Intel server cores (and some others) caps vectors at 256 bits to avoid the clock
#: penalty of early AVX-512 parts; these float32 loops are compute-bound, so 512-bit vectors
#: make them faster (maem-bench --load large, alternating runs), while the same setting
#: process-wide (NUMBA_CPU_FEATURES) slowed the float64 triangulation kernel: so per function
_WIDE = '"prefer-vector-width"="512"'


#: LLVM function attribute: a float32 1/sqrt (``afn``) is the hardware estimate alone, no
#: Newton step. x86's estimates are documented within 1.5 * 2^-12 relative (rsqrtps; the
#: AVX-512 rsqrt14ps that 512-bit loops take, 2^-14), inside epipolar._RSQRT_ERR = 2^-10, so
#: the error bound covers them (and epipolar._rsqrt_within_bound checks it at first use). A
#: Newton step is 4 vector operations, twice per point of ~36: leaving it out (with
#: refined_pair's second try for the pairs the wider bound cannot settle) saves about that
#: share of the kernel levels' arithmetic.
#: Only on x86-64: other targets' estimates are coarser (AArch64's frsqrte: 8 bits), so they
#: keep LLVM's Newton steps
_ESTIMATE = '"reciprocal-estimates"="sqrtf:0,vec-sqrtf:0"'


def _function_attribute(attribute: str, doc: str, x86_only: bool = False):
    """An intrinsic that marks the calling kernel with the LLVM function attribute
    ``attribute`` (x86_only: on x86-64 targets only). A no-op where llvmlite's function
    attributes are not the set of printed strings they are today."""
    @nb.extending.intrinsic
    def intrinsic(typingctx):
        def codegen(context, builder, signature, args):
            attributes = builder.function.attributes
            x86 = builder.module.triple.startswith(("x86_64", "amd64"))
            if isinstance(attributes, set) and (x86 or not x86_only):
                # set.add: llvmlite's own add() accepts only LLVM's keyword attributes
                set.add(attributes, attribute)
            return context.get_dummy_value()
        return nb.types.none(), codegen
    intrinsic.__doc__ = doc
    return intrinsic


wide_vectors = _function_attribute(_WIDE, "Mark the calling kernel with _WIDE (else only "
                                          "narrower vectors).")
estimated_rsqrt = _function_attribute(_ESTIMATE, "Mark the calling float32 kernel with "
                                                 "_ESTIMATE (x86-64 only).", x86_only=True)


@inline
def points(like, address, start, count):
    """count coordinates from element start of the detection at address: a view without
    reference counting (a typed list of the cameras' arrays pays it on every access in the
    hot loop); the caller keeps the arrays alive."""
    return nb.carray(pointer_like(like, address + start * like.itemsize), (count,))


#: squared line norm at (or below) which a point is at the epipole (F of unit norm)
_Q_EPIPOLE = EPIPOLE_NORM ** 2


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
#: of a block: no gain, the requests queue up and the arithmetic waits behind them.) This
#: helps most where memory is slow (the full level, the 1/8 screen of the large load, in
#: alternating runs); chunks of 128 gain the same, of 512 about half
CHUNK = 256


#: fewest points per detection for which the block loops prefetch the next pair's blocks: a
#: coarser screen's gathered points stay in cache (on a large-load frame set the 1/32 screen's
#: 576 points per detection are 1.8 MB in all), where the chunked loop only adds work
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
        ak = a[2 * k0:2 * k1]
        bk = b[2 * k0:2 * k1]
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
    epipolar._RSQRT_ERR_REFINED): the second try of a pair the estimate's bound cannot
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
        ew, w = b_terms(b[2 * j], b[2 * j + 1], l0, l1, l2, wa, g0, g1, g3, g4, g6, g7,
                        symmetric)
        p1 += ew
        s1 += w
        q1 += ew * w
        ew, w = b_terms(d[2 * j], d[2 * j + 1], l0, l1, l2, wa, g0, g1, g3, g4, g6, g7,
                        symmetric)
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
        ak = a[2 * k0:2 * k1]
        bk = b[2 * k0:2 * k1]
        dk = d[2 * k0:2 * k1]
        if symmetric:
            dp1, ds1, dq1, dp2, ds2, dq2 = chunk32x2(ak, bk, dk, g0, g1, g2, g3, g4, g5, g6,
                                                     g7, g8, True)
        else:
            dp1, ds1, dq1, dp2, ds2, dq2 = chunk32x2(ak, bk, dk, g0, g1, g2, g3, g4, g5, g6,
                                                     g7, g8, False)
        p1 += dp1
        s1 += ds1
        q1 += dq1
        p2 += dp2
        s2 += ds2
        q2 += dq2
    return ((np.float64(p1), np.float64(s1), np.float64(q1)),
            (np.float64(p2), np.float64(s2), np.float64(q2)))


@inline
def block_range(x, ranges, d, r):
    """(min, max) of all coordinates of detection d's block r of float32 points x (2m,),
    cached in ranges[d, r] (a decoder's, epipolar.screen_copies, when given); (inf, -inf) if
    one is NaN or inf. The cached case inlined (the kernel asks ~3 times a pair and block),
    the scan a call."""
    if ranges[d, r, 0] == ranges[d, r, 0]:
        return ranges[d, r, 0], ranges[d, r, 1]
    return scan_range(x, ranges, d, r)


@plain
def scan_range(x, ranges, d, r):
    """block_range of a block not cached yet: scanned, then cached."""
    wide_vectors()
    lo, hi = key_range(x.view(np.int32))
    ranges[d, r, 0], ranges[d, r, 1] = key_values(lo, hi)
    return ranges[d, r, 0], ranges[d, r, 1]


_LOW31 = np.int32(0x7FFFFFFF)


@inline
def key_range(bits):
    """(min, max) ordered int32 keys of float32 values (their int32 bits): ordered keys of
    the float bits, so the min/max reductions vectorise."""
    lo = np.int32(2147483647)
    hi = np.int32(-2147483648)
    for k in range(bits.shape[0]):
        b = bits[k]
        # int32 throughout and selects, not min(): the loop vectorises
        key = np.int32(b ^ (np.int32(b >> np.int32(31)) & _LOW31))
        lo = key if key < lo else lo
        hi = key if key > hi else hi
    return lo, hi


@inline
def key_values(lo, hi):
    """key_range's keys as (min, max) float values; (inf, -inf) if a value is NaN or inf."""
    if lo <= _KEY_NEG_INF or hi >= _KEY_POS_INF:
        return np.inf, -np.inf
    keys = np.empty(2, dtype=np.int32)
    keys[0] = lo ^ ((lo >> 31) & _LOW31)
    keys[1] = hi ^ ((hi >> 31) & _LOW31)
    vals = keys.view(np.float32)
    return np.float64(vals[0]), np.float64(vals[1])


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
    lb = ((G[t, 0, 0] + G[t, 0, 1]) * xb0 + (G[t, 1, 0] + G[t, 1, 1]) * xb1 + G[t, 2, 0]
          + G[t, 2, 1])
    lmax = max(la, lb) if h != 1.0 else la
    p, s, q = sums
    # a point at the epipole (float64 rule: ||l_12|| <= EPIPOLE_NORM = epi in g's units)
    # has a float32 line norm within the rounding bound 6 u L of that: its weight, and so
    # the block's weight sum, reaches 1 / (epi + 6 u L); such a block goes to float64
    # (part inf)
    if not s * (epi + 6.0 * _U32 * lmax) * (1.0 + 2.0 * rsqrt_err) < 1.0:
        return np.inf, np.inf
    part = h * p
    # sum |e| (wa^2 + wb^2) <= sum |e| w^2 bounds the line-norm term of both sides
    err = (10.0 * _U32 * bil * h * s + 8.0 * _U32 * h * lmax * q
           + (rsqrt_err + (m + 8) * _U32) * part)
    return part, err * (1.0 + _BOUND_SLACK)


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
        p, c = block64(a[2 * lo:2 * hi], b[2 * lo:2 * hi], fs, fk, ha, symmetric)
        total += p if p == p else np.inf  # NaN: undefined line -> cannot pass
        count += c
        seen += hi - lo
        # count + points still to come bounds the final count from above
        if early_exit and total >= tau * (count + (n - seen)):
            last = r
            break
    return total, count, last


@inline
def pair64_into(s, like, det_addr, pa, pb, fs, fk, blocks, n, tau, early_exit, h, symmetric,
                sums, used, last):
    """pair64 of pair s (detections pa[s], pb[s] under fs[fk[s]]) into sums, used, last."""
    sums[s], used[s], last[s] = pair64(points(like, det_addr[pa[s]], 0, 2 * n),
                                       points(like, det_addr[pb[s]], 0, 2 * n), fs, fk[s],
                                       blocks, n, tau, early_exit, h, symmetric)


@plain
def present64(a, b):
    """Points of a block that both detections have: block64's test (the float64 sum of the
    four coordinates is not NaN), without the distances."""
    count = 0
    for k in range(a.shape[0] // 2):
        s = (np.float64(a[2 * k]) + np.float64(a[2 * k + 1]) + np.float64(b[2 * k])
             + np.float64(b[2 * k + 1]))
        count += np.int64(s == s)
    return count


@plain
def rest_present(a, b, blocks, after):
    """Points of the blocks after block index ``after`` that both a and b (2n,) have."""
    count = 0
    for r in range(after + 1, blocks.shape[0]):
        lo = blocks[r, 0]
        hi = blocks[r, 1]
        count += present64(a[2 * lo:2 * hi], b[2 * lo:2 * hi])
    return count


@inline
def pair_bound(G, k, ranges, i, j, r, sums3, h, m, rsqrt_err=_RSQRT_ERR):
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
    on every pair, which showed in the 1/32 screen of the large load)."""
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
def single(s, r, lo, hi, rest, like, det_addr, pa, pb, ranges, g, G, fs, fk, h,
           symmetric, tau, early_exit, sums, err, used, alive, fetch):
    """Block r = points lo:hi of pair s alone (fetch: in chunks, prefetching the next pair's
    blocks)."""
    i, j, ab, bb, finite = pair_block(s, r, lo, hi, like, det_addr, pa, pb, ranges)
    p = np.inf
    e = np.inf
    if finite:  # no NaN or inf coordinate
        next_a, next_b = next_blocks(s, pa, pb, det_addr, 2 * lo * like.itemsize, fetch)
        p, e = pair_bound(G, fk[s], ranges, i, j, r,
                          block32(ab, bb, g, fk[s], symmetric, fetch, next_a, next_b), h,
                          hi - lo)
    if p < np.inf and e < np.inf:
        settle(s, p, e, hi - lo, rest, tau, early_exit, sums, err, used, alive)
    else:
        settle64(s, ab, bb, fs, fk[s], rest, h, symmetric, tau, early_exit, sums, err, used,
                 alive)


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
    t = np.array([f[0], f[1], h02, f[3], f[4], h12, cb0 * f[0] + cb1 * f[3] + f[6],
                  cb0 * f[1] + cb1 * f[4] + f[7], cb0 * h02 + cb1 * h12 + h22])
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
        ab = ac[2 * lo:2 * hi]
        bb = bc[2 * lo:2 * hi]
        lo_a, hi_a = block_range(ab, ranges, 0, r)
        lo_b, hi_b = block_range(bb, ranges, 1, r)
        p = np.inf
        e = np.inf
        if lo_a <= hi_a and lo_b <= hi_b:
            p, e = pair_bound(G, 0, ranges, 0, 1, r, block32_refined(ab, bb, g, 0, symmetric),
                              h, hi - lo, _RSQRT_ERR_REFINED)
        if p < np.inf and e < np.inf:
            total += p
            bound += e
            count += hi - lo
        else:
            p, k = block64(a[2 * lo:2 * hi], b[2 * lo:2 * hi], fs, fk[s], h, symmetric)
            total += p if p == p else np.inf
            count += k
    return total, bound, count


@plain
def sums_kernel(like, det_addr, ranges, fs, fk, pa, pb, blocks, n, tau, early_exit,
                symmetric, mixed, refine, count_rest):
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
        return ordered_sums(like, det_addr, ranges, fs, fk, pa, pb, blocks, n, tau,
                            early_exit, symmetric, mixed, refine, count_rest)
    perm = locality_order(pa, pb, fk, ranges.shape[0], LOCALITY_BLOCKS)
    got = ordered_sums(like, det_addr, ranges, fs, fk[perm], pa[perm], pb[perm], blocks, n,
                       tau, early_exit, symmetric, mixed, refine, count_rest)
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
        total, used = _with_rest(like, det_addr, pa, pb, blocks, n, used, last, count_rest)
        return sums, total, used
    # each camera pair's float32 F, then the blocks outermost: one block of every detection
    # of the frame stays in cache while all its candidate pairs read it, instead of each pair
    # streaming whole detections from memory
    g, G = float32_f(fs)
    # run_end[s]: end of s's run, the pairs of its a-side detection in its camera pair
    # (sorted together); their lines and weights in a are computed once, two pairs at a time
    run_end = np.empty(S, dtype=np.int64)
    for s in range(S - 1, -1, -1):
        same = s + 1 < S and pa[s + 1] == pa[s] and fk[s + 1] == fk[s]
        run_end[s] = run_end[s + 1] if same else s + 1
    err = np.zeros(S)
    alive = np.ones(S, dtype=np.bool_)  # not rejected early
    seen = 0
    for r in range(blocks.shape[0]):
        lo = blocks[r, 0]
        hi = blocks[r, 1]
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
                i = pa[t]
                ab = points(like, det_addr[i], 2 * lo, 2 * (hi - lo))
                j = pb[first]
                bb = points(like, det_addr[j], 2 * lo, 2 * (hi - lo))
                j2 = pb[t]
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
                    single(first, r, lo, hi, n - seen, like, det_addr, pa, pb,
                           ranges, g, G, fs, fk, h, symmetric, tau, early_exit,
                           sums, err, used, alive, fetch)
                    single(t, r, lo, hi, n - seen, like, det_addr, pa, pb,
                           ranges, g, G, fs, fk, h, symmetric, tau, early_exit,
                           sums, err, used, alive, fetch)
                first = -1
            if first >= 0:
                single(first, r, lo, hi, n - seen, like, det_addr, pa, pb, ranges,
                       g, G, fs, fk, h, symmetric, tau, early_exit, sums, err,
                       used, alive, fetch)
            s = run_end[s]
        for t in range(S):  # where this block's early exits stopped
            if not alive[t] and last[t] < 0:
                last[t] = r
    for s in range(S):
        if not alive[s] or decided(sums[s], err[s], used[s], tau):
            continue
        # the bound does not settle the decision (the mean is within ~2^-10 of tau): again
        # with the refined 1/sqrt (~2^-20), then float64 throughout
        if refine:
            total, bound, count = refined_pair(s, like, det_addr, pa, pb, blocks, n, fs, fk,
                                               h, symmetric)
            if decided(total, bound, count, tau):
                sums[s] = total
                used[s] = count
                continue
        pair64_into(s, like, det_addr, pa, pb, fs, fk, blocks, n, tau, early_exit, h,
                    symmetric, sums, used, last)
    total, used = _with_rest(like, det_addr, pa, pb, blocks, n, used, last, count_rest)
    return sums, total, used


@plain
def _with_rest(like, det_addr, pa, pb, blocks, n, used, last, count_rest):
    """(used with the points after each early exit when count_rest, points summed)."""
    total = used.copy()
    if count_rest:
        for s in range(used.shape[0]):
            if 0 <= last[s] < blocks.shape[0] - 1:
                total[s] += rest_present(points(like, det_addr[pa[s]], 0, 2 * n),
                                         points(like, det_addr[pb[s]], 0, 2 * n), blocks,
                                         last[s])
    return total, used


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
            copy_run(points(like, det_addr[d], 2 * r * period, 2 * run), d, r, out, every,
                     coarse)


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
def scan_gather_runs(like, det_addr, n, block, run, period, out, every, coarse, ranges,
                     out_ranges, coarse_ranges):
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
            if (first_inf < 0 and not ranges[d, b, 0] <= ranges[d, b, 1] and
                    has_inf(block_points(like, det_addr[d], n, block, b).view(np.uint32))):
                first_inf = d
        for r in range(runs):
            copy_run(points(like, det_addr[d], 2 * r * period, 2 * run), d, r, out, every,
                     coarse)
        # the copies' rows, just written (in cache)
        address_ranges(out, out.ctypes.data + d * out.strides[0], out.shape[1] // 2, block,
                       out_ranges, d)
        if every > 0:
            address_ranges(coarse, coarse.ctypes.data + d * coarse.strides[0],
                           coarse.shape[1] // 2, block, coarse_ranges, d)
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
        qk = q[start:min(start + step, n)]
        ok = out[start:min(start + step, n)]
        for k in range(qk.shape[0]):
            ok[k] = np.float32(1.0) / np.sqrt(qk[k])


@jit32
def rsqrt32(q, out, step):
    """rsqrt32_chunks compiled as block32 is (the probe of epipolar._rsqrt_within_bound)."""
    wide_vectors()
    estimated_rsqrt()
    rsqrt32_chunks(q, out, step)


@jit32
def rsqrt32_refined(q, out, step):
    """rsqrt32_chunks compiled as block32_refined is (the probe of
    epipolar._rsqrt_within_bound)."""
    wide_vectors()
    rsqrt32_chunks(q, out, step)
