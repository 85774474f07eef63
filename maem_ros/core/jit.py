"""One home for compiling core's optional numba kernels (clustering, procrustes and
triangulation kernels; the epipolar kernel keeps its own fast-math variants)."""

from __future__ import annotations

from typing import Literal, TypedDict

try:  # numba is optional: every kernel has a numpy path with the same results
    import numba as _numba
except ImportError:  # pragma: no cover - exercised only without numba
    _numba = None  # type: ignore[assignment]  # None = numba missing


class NjitOptions(TypedDict):
    """The numba.njit options every kernel shares (typed, so ``njit(**options)`` type-checks)."""

    cache: bool
    error_model: Literal["python", "numpy"]
    boundscheck: bool
    nogil: bool


def have_numba() -> bool:
    return _numba is not None


def jit(fn=None, *, inline: bool = False):
    """numba.njit with the on-disk cache, numpy's error model, no bounds checks and no GIL
    (``inline``: inlined into its callers, for the small helpers of hot loops), or ``fn``
    unchanged without numba (then the numpy paths run and it is never called). Usable as
    ``@jit``, ``@jit(inline=True)`` or ``jit(fn, inline=True)`` (to compile another module's
    elementwise function). Module-level functions, not closures: numba's cache key hashes a
    closure's cells, and a captured dispatcher hashes differently in every process."""

    def compile_(f):
        if _numba is None:
            return f
        return _numba.njit(
            cache=True,
            error_model="numpy",
            boundscheck=False,
            nogil=True,
            inline="always" if inline else "never",
        )(f)

    return compile_ if fn is None else compile_(fn)
