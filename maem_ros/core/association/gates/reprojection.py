"""The bbox-centre reprojection gate (MAEM stage 2, step 2): a pair of detections of two cameras
passes when the DLT point of their two bbox centres reprojects into both views within
tau_reproj_bbox px (mean of the two errors, or max) and lies in front of both cameras.

The epipolar lower bound of the error (geometry.multiview.pair_reprojection_bound) rejects
most pairs of different people without triangulating; the rest get the DLT. The bound keeps
a relative margin for rounding, so the decisions are exactly the DLT's. With numba, the
enumeration of a frame set's pairs and the gate run in one pass (reprojection_kernel).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from maem_ros.core.geometry.multiview import pair_reprojection_bound, pair_reprojection_errors
from maem_ros.core.jit import have_numba

#: relative margin of the reprojection bound over tau_reproj_bbox before it rejects alone
#: (its own rounding is ~1e-13 relative)
BOUND_MARGIN = 1e-6


def enumerate_pairs(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (i, j) of every pair of rows of different cameras (camera c's rows are
    ``offsets[c]:offsets[c + 1]``), grouped by camera pair a < b in order, each group
    row-major (i, then j)."""
    sizes = np.diff(offsets)
    a, b = np.triu_indices(sizes.size, 1)
    count = sizes[a] * sizes[b]
    some = count > 0
    a, b, count = a[some], b[some], count[some]
    group = np.repeat(np.arange(count.size), count)
    k = np.arange(int(count.sum())) - (np.cumsum(count) - count)[group]
    width = sizes[b][group]
    return offsets[a][group] + k // width, offsets[b][group] + k % width


def reprojection_ok(
    stack: np.ndarray,
    P: np.ndarray,
    cam: np.ndarray,
    centers: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    tau: float,
    reduce: str,
) -> np.ndarray:
    """(S,) pairs of views (i[s], j[s]) whose bbox-centre reprojection error is under tau px.

    stack (C,C,3,3) F[a, b] both ways; P (C,3,4) rectified projections; cam (N,) each view's
    camera; centers (N,2) px; reduce ``mean`` or ``max``."""
    bound = pair_reprojection_bound(stack, cam, centers, i, j, reduce)
    ok = np.zeros(i.size, bool)
    todo = np.flatnonzero(~(bound > tau * (1.0 + BOUND_MARGIN)))
    if todo.size:
        errors = pair_reprojection_errors(P[cam], centers, i[todo], j[todo], reduce)
        ok[todo] = errors < tau
    return ok


def reprojection_kernel(backend: str) -> Callable | None:
    """The numba pass of enumeration + reprojection gate (reprojection_kernel; same pairs,
    order and decisions as enumerate_pairs + reprojection_ok), or None for the numpy path
    (``backend`` numpy, or numba not installed)."""
    if backend == "numpy" or not have_numba():
        return None
    from maem_ros.core.association.gates.reprojection_kernel import reprojection_gate

    return reprojection_gate


def warmup(backend: str = "auto") -> None:
    """Compile (or load from numba's on-disk cache) the reprojection kernel now."""
    kernel = reprojection_kernel(backend)
    if kernel is not None:
        kernel(
            np.arange(3, dtype=np.int64),
            np.zeros((2, 2, 3, 3)),
            np.zeros((2, 3, 4)),
            np.zeros((2, 2)),
            1.0,
            BOUND_MARGIN,
            False,
        )
