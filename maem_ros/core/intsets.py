"""Distinct values of integer id and code arrays (detections, cameras, pair codes) on the
per-frame paths.

np.unique is the obvious call, but numpy 2.4 (the version installed) takes a hash table for
a plain ``np.unique(x)``, which is an order of magnitude slower than a sort on these small
int64 arrays, and ``return_inverse`` adds an argsort; called ~10 times per frame set, that was
a visible share of the large load's association. Same results as np.unique, from a sort or,
for ids below a small bound, a count.
"""

from __future__ import annotations

import numpy as np


def sorted_unique(x: np.ndarray) -> np.ndarray:
    """The distinct values of integer array x, ascending (np.unique(x))."""
    s = np.sort(np.asarray(x).reshape(-1))
    keep = np.empty(s.size, bool)
    keep[:1] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def unique_inverse(x: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """(values, inverse) of non-negative integers x < bound, as np.unique(x,
    return_inverse=True): values ascending, x == values[inverse]. O(x.size + bound), for
    bounds of the order of the ids' count (detections, camera pairs)."""
    x = np.asarray(x).reshape(-1)
    present = np.zeros(bound, bool)
    present[x] = True
    values = np.flatnonzero(present)
    rank = np.cumsum(present) - 1
    return values, rank[x]
