"""Whether the compiled float32 1/sqrt of the epipolar kernels is as accurate as the mixed
kernel's error bound assumes (core/association/gates/epipolar_constants.py): a probe of the
instructions LLVM picked for this CPU, run once per process (epipolar.py asks before it takes
the float32 path)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from maem_ros.core.association.gates.epipolar_constants import RSQRT_ERR, RSQRT_ERR_REFINED


@lru_cache(maxsize=1)
def rsqrt_within_bound() -> bool:
    """Whether the compiled float32 1/sqrt of the kernels (the instructions LLVM picks for
    this CPU) is within half of RSQRT_ERR of the exact value; if not, the mixed kernel's
    error bound would not hold, and "mixed" runs in float64 instead."""
    from maem_ros.core.association.gates.epipolar_kernel import rsqrt32

    return _rsqrt_probe(rsqrt32) <= RSQRT_ERR / 2


@lru_cache(maxsize=1)
def refined_rsqrt_within_bound() -> bool:
    """Whether the refined float32 1/sqrt of a pair's second try is within half of
    RSQRT_ERR_REFINED; if not, pairs the first bound cannot settle go to float64 at once."""
    from maem_ros.core.association.gates.epipolar_kernel import rsqrt32_refined

    return _rsqrt_probe(rsqrt32_refined) <= RSQRT_ERR_REFINED / 2


def _rsqrt_probe(kernel) -> float:
    """Largest relative error of a compiled float32 1/sqrt ``kernel(q, out, step)``. An
    estimate depends on the mantissa and the exponent's parity: every 61st float32 in [1, 4)
    (8 or more arguments in every table cell of the 12- and 14-bit estimates) through the
    widest vector loop and through the narrower remainder code (chunks shorter than one
    vector), and a sweep over the whole exponent range."""
    every = np.arange(
        np.float32(1.0).view(np.int32), np.float32(4.0).view(np.int32), 61, dtype=np.int32
    ).view(np.float32)
    q = np.concatenate([every, np.geomspace(1e-30, 1e30, 200_003).astype(np.float32)])
    worst = 0.0
    for probe, step in ((q, q.size), (every, _REMAINDER_PROBE)):
        got = np.empty_like(probe)
        kernel(probe, got, step)
        exact = 1.0 / np.sqrt(probe.astype(np.float64))
        worst = max(worst, float(np.max(np.abs(got / exact - 1.0))))
    return worst


#: arguments per chunk of the remainder probe: fewer than a 512-bit vector of float32 lanes
_REMAINDER_PROBE = 15
