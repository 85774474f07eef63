"""Constants of the epipolar gate shared by its numpy code (epipolar, point_rows, screening)
and its numba kernels (epipolar_kernel): the block layout, the epipole rule, the float32 error
bound's terms and the screening runs. One home, so the kernels import no numpy module."""

from __future__ import annotations

#: the gate's backends and the numba kernel's arithmetic
BACKENDS = ("auto", "numba", "numpy")
PRECISIONS = ("mixed", "float64")

#: points per contiguous block (SIMD-friendly, long enough that the per-block overhead stays
#: small and that a block's points stream from memory as one run; the early exit is tested
#: once per block, so longer blocks sum a little more of a rejected pair); blocks are visited
#: in a fixed shuffled order
BLOCK = 4096
#: a point whose line has ||(F x)_12|| <= EPIPOLE_NORM ||F|| is at the epipole (its line is
#: rounding noise): distance inf, the pair is rejected. ~1e-6 px from the epipole of a
#: typical pixel F; one definition for every backend and precision
EPIPOLE_NORM = 1e-12
#: seed of the fixed block order (any fixed value; part of the definition of "the order")
ORDER_SEED = 20240611
#: float32 unit roundoff
U32 = 2.0**-24
#: relative error bound of the float32 1/sqrt of the kernels: the hardware estimate alone on
#: x86-64 (documented |rel err| <= 1.5 * 2^-12, 3.7e-4; rsqrt14ps 2^-14; 2^-10 leaves a margin
#: of ~2.7), elsewhere the estimate with LLVM's Newton steps. Checked at first use
#: (rsqrt_check.rsqrt_within_bound)
RSQRT_ERR = 2.0**-10
#: the same of the refined float32 1/sqrt that a pair's second try takes (the estimate plus
#: one Newton step in float32: ~3 * 2^-24 + 1.7 * 2^-24; 2^-20 leaves a margin of ~3)
RSQRT_ERR_REFINED = 2.0**-20
#: relative slack on the error bound for its own (second-order) rounding
BOUND_SLACK = 1e-3
#: float32 bit patterns mapped to ordered int32 keys: keys of -inf and +inf (finite in between)
KEY_NEG_INF = -2139095041
KEY_POS_INF = 2139095040
#: consecutive points per screening run (8 float32 (u, v) = one 64-byte cache line)
SCREEN_RUN = 8
#: fewest screening points worth a screen (below this the full set is cheap anyway)
SCREEN_MIN_POINTS = 64
