"""The mesh gate's screening levels: pairs decided on fixed-topology subsets of the vertices
(runs of SCREEN_RUN consecutive ones, 1/stride of them), coarse to fine, the full set only
within a margin of tau (:func:`frame_screened_means`), and the contiguous copies of the subsets
with their block ranges that a camera frame's one preparing pass makes
(:func:`screen_copies`). The sums are core.association.gates.epipolar's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from maem_ros.core.association.gates.epipolar import (
    FramePairs,
    PairMatrices,
    detections_read,
    frame_pairs,
    gather_buffer,
    level_sums,
    numba_kernels,
)
from maem_ros.core.association.gates.epipolar_constants import BLOCK, SCREEN_MIN_POINTS, SCREEN_RUN
from maem_ros.core.association.gates.point_rows import PointRows, point_rows
from maem_ros.core.jit import have_numba

#: one screening level: the subset of every camera's points (:func:`screen_rows`) and its margin
#: (px): subset means within it of tau go on to the next level
ScreenLevel = tuple[Mapping[int, PointRows], float]


def screen_rows(x: np.ndarray | PointRows, stride: int) -> PointRows | None:
    """The screening subset of (N,n,2) points (or their full-set :class:`PointRows`) as the
    kernel reads them: runs of SCREEN_RUN consecutive points, one run in every
    ``SCREEN_RUN * stride`` (1/stride of the points, the same fixed-topology ids in every
    detection), described over x's own memory (no copy here; the numba backend gathers the
    runs of the detections that take part once per call). Runs rather than single points so
    a screen reads 1/stride of the cache lines (every other point of a strided subset shares
    a line with a skipped one). None when the screen is off (stride 1) or would keep too few
    points to screen with."""
    full = point_rows(x)
    if full.run:
        raise ValueError("screen_rows: expected the full point set, got a subset")
    period = SCREEN_RUN * stride
    runs = full.n // period
    if stride <= 1 or runs * SCREEN_RUN < SCREEN_MIN_POINTS:
        return None
    return PointRows(full.flat, full.rows, runs * SCREEN_RUN, SCREEN_RUN, period)


class ScreenCopies(NamedTuple):
    """What the preparing pass over one camera frame's (N,n,2) float32 points leaves for the
    mesh gate (:func:`screen_copies`, PairGates.prepare)."""

    #: {stride: (N,m,2) float32 read-only}: each screening subset, contiguous
    copies: dict[int, np.ndarray]
    #: {stride: (N, blocks, 2) float32 read-only}: PointRows.ranges of the full set
    #: (stride 1) and of each copy made in the one pass (empty without numba)
    block_ranges: dict[int, np.ndarray]
    #: the first detection with an infinite coordinate (-1: none; NaN = missing is allowed)
    first_inf: int
    #: px, the smallest and the largest coordinate present (u and v together, NaN = missing
    #: ignored; NaN when none is present or an infinite one was found)
    extremes: tuple[float, float]


def screen_copies(x: np.ndarray, strides: Sequence[int]) -> ScreenCopies:
    """The screening subsets of one camera's (N,n,2) float32 points for each of ``strides``
    (:func:`screen_rows`) copied contiguous (strides whose screen is off left out), the full
    set's and the copies' block ranges, and the first detection with an infinite coordinate.

    For PairGates.prepare, as each camera frame arrives (off the frame set's critical path):
    with numba, one pass scans each detection (its block ranges) and copies its runs (of the
    finest subset and of one coarser subset nested in it) while they are in cache. The gate
    then reads the copies where it would gather the same runs from scattered cache lines,
    and the ranges where its kernel would scan the points again
    (epipolar._known_ranges). The pass is also the points' finiteness check and finds their
    extremes (the full set's block ranges), so a receiver need not make one of its own."""
    x = np.asarray(x, dtype=np.float32)
    full = point_rows(x)
    screens = [(s, screen_rows(full, s)) for s in sorted(set(int(v) for v in strides))]
    levels = [(s, rows) for s, rows in screens if rows is not None]  # finest first
    if not have_numba() or full.count == 0 or not levels:
        bad = np.flatnonzero(np.isinf(x).any(axis=(1, 2)))
        copies = {s: rows._gather(rows.rows) for s, rows in levels}
        first_inf = int(bad[0]) if bad.size else -1
        return ScreenCopies(_read_only(copies), {}, first_inf, _extremes(x, None, first_inf))
    (stride, fine), rest = levels[0], levels[1:]
    nested = [(s, rows) for s, rows in rest if rows.period % fine.period == 0]
    coarse_stride, coarse = nested[0] if nested else (0, None)
    out = np.empty((full.count, 2 * fine.n), np.float32)
    every = coarse.period // fine.period if coarse is not None else 0
    inner = np.empty((full.count, 2 * coarse.n) if coarse is not None else (0, 0), np.float32)
    ranges = {1: _ranges_buffer(full.count, full.n), stride: _ranges_buffer(full.count, fine.n)}
    inner_ranges = _ranges_buffer(full.count, coarse.n if coarse is not None else 0)
    det_addr = full.flat.__array_interface__["data"][0] + full.rows * full.flat.itemsize
    first_inf = numba_kernels().scan_gather_runs(
        full.flat,
        det_addr,
        full.n,
        BLOCK,
        fine.run,
        fine.period,
        out,
        every,
        inner,
        ranges[1],
        ranges[stride],
        inner_ranges,
    )
    copies = {stride: out.reshape(full.count, fine.n, 2)}
    if coarse is not None:
        copies[coarse_stride] = inner.reshape(full.count, coarse.n, 2)
        ranges[coarse_stride] = inner_ranges
    for s, rows in rest:  # a level not nested in the finest one: gathered on its own
        if s not in copies:
            copies[s] = rows._gather(rows.rows)
    return ScreenCopies(
        _read_only(copies), _read_only(ranges), int(first_inf), _extremes(x, ranges[1], int(first_inf))
    )


def _extremes(x: np.ndarray, block_ranges: np.ndarray | None, first_inf: int) -> tuple[float, float]:
    """(smallest, largest) coordinate of the (N,n,2) points, NaN ignored (NaN, NaN when none
    is present or one is infinite), from the blocks' ranges where the scan gave them: a block
    holding a NaN has none (inf, -inf), and only its detections are reduced again."""
    if first_inf >= 0 or x.size == 0:
        return np.nan, np.nan
    if block_ranges is None:
        return float(np.fmin.reduce(x, axis=None)), float(np.fmax.reduce(x, axis=None))
    low, high = block_ranges[..., 0], block_ranges[..., 1]
    whole = low <= high
    lo = float(low[whole].min()) if whole.any() else np.nan
    hi = float(high[whole].max()) if whole.any() else np.nan
    with_nan = np.flatnonzero(~whole.all(axis=1))
    if with_nan.size:
        rest = x[with_nan]
        lo = float(np.fmin(lo, np.fmin.reduce(rest, axis=None)))
        hi = float(np.fmax(hi, np.fmax.reduce(rest, axis=None)))
    return lo, hi


def _ranges_buffer(count: int, n: int) -> np.ndarray:
    """(count, blocks of n points, 2) float32 for PointRows.ranges."""
    return np.empty((count, -(-n // BLOCK), 2), np.float32)


def _read_only(arrays: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    for a in arrays.values():
        a.setflags(write=False)
    return arrays


def _gathered_screens(
    plan: FramePairs, screens: Sequence[ScreenLevel], backend: str
) -> Sequence[ScreenLevel]:
    """The screening levels with the subsets of the plan's detections gathered once,
    contiguous, for the numba kernel: one pass over each detection's points copies the finest
    level's runs and, of them, a coarser level's (its runs are every k-th of the finest's when
    its period is a multiple of the finest's). The coarse level's own gather, a second pass
    over scattered cache lines, took 1.1-1.2 ms of a large-load frame set; the copies add
    ~0.4 ms to the screen's pass (2-core Xeon VM). The levels as they are where that does not
    apply (the numpy backend reads the runs in place; other layouts are gathered level by
    level in the kernel call)."""
    if not screens or len(screens) > 2 or backend == "numpy" or not have_numba():
        return screens
    levels = [{c: point_rows(level[c]) for c in plan.cams} for level, _ in screens]
    fine = levels[-1]
    rows = [fine[c] for c in plan.cams]
    every = 0
    if len(levels) == 2:
        coarse = levels[0]
        if any(
            coarse[c].flat is not fine[c].flat
            or coarse[c].rows is not fine[c].rows
            or coarse[c].run != fine[c].run
            or coarse[c].period % fine[c].period
            for c in plan.cams
        ):
            return screens
        every = coarse[plan.cams[0]].period // fine[plan.cams[0]].period
        if any(coarse[c].period != every * fine[c].period for c in plan.cams):
            return screens
    if len({(r.run, r.period, r.n, r.flat.dtype) for r in rows}) > 1 or not rows[0].run:
        return screens
    # flats keeps the message buffers referenced while the kernel reads them by address;
    # slot: each detection's place among those gathered
    flats = [r.flat for r in rows]
    dets, slot, det_addr = detections_read(plan, plan.key_a, plan.key_b, flats, [r.rows for r in rows])
    run, period, n, dtype = rows[0].run, rows[0].period, rows[0].n, rows[0].flat.dtype
    out = gather_buffer(dets.size * 2 * n, dtype, 1).reshape(dets.size, 2 * n)
    n_coarse = levels[0][plan.cams[0]].n if every else 0
    inner = gather_buffer(dets.size * 2 * n_coarse, dtype, 2).reshape(dets.size, 2 * n_coarse)
    numba_kernels().gather_runs(flats[0], det_addr, run, period, out, every, inner)
    gathered = []
    for (_level, margin), buffer, size in zip(
        screens, [inner, out][-len(screens) :], [n_coarse, n][-len(screens) :]
    ):
        flat = buffer.reshape(-1).view()
        flat.setflags(write=False)
        at = slot.clip(0) * (2 * size)  # each detection's row in the buffer (unread if absent)
        gathered.append(
            (
                {
                    c: PointRows(flat, at[plan.offsets[k] : plan.offsets[k + 1]], size)
                    for k, c in enumerate(plan.cams)
                },
                margin,
            )
        )
    return gathered


def screened_means(
    full: tuple[PointRows, PointRows],
    screen: tuple[PointRows, PointRows] | None,
    F: np.ndarray,
    ia: np.ndarray,
    jb: np.ndarray,
    tau: float,
    margin: float,
    symmetric: bool = True,
    early_exit: bool = True,
    backend: str = "auto",
    precision: str = "mixed",
) -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of detection pairs (ia[s] in a, jb[s] in b) of one camera pair with
    one screening level (or None): :func:`frame_screened_means` of that camera pair."""
    ia = np.asarray(ia)
    return frame_screened_means(
        dict(enumerate(full)),
        [] if screen is None else [(dict(enumerate(screen)), margin)],
        {(0, 1): F},
        np.zeros(ia.shape, np.int64),
        ia,
        np.ones(ia.shape, np.int64),
        jb,
        tau,
        symmetric,
        early_exit,
        backend,
        precision,
    )


def frame_screened_means(
    full: Mapping[int, PointRows],
    screens: Sequence[ScreenLevel],
    F: Mapping[tuple[int, int], np.ndarray] | PairMatrices,
    cam_a: np.ndarray,
    det_a: np.ndarray,
    cam_b: np.ndarray,
    det_b: np.ndarray,
    tau: float,
    symmetric: bool = True,
    early_exit: bool = True,
    backend: str = "auto",
    precision: str = "mixed",
) -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of the detection pairs of a frame (as :func:`frame_sums`): (keep (S,)
    bool, mean (S,) px over the points the decision used, points evaluated); one kernel call
    per level for every camera pair at once.

    Without screening levels (empty) every pair is decided on the full point sets (exact: the
    mean over all points both detections have, ``keep = mean < tau``). With them (coarse to
    fine; each the same fixed-topology subset of every camera's points and a margin), the
    pairs still open are taken over each level's subset in turn: a pair whose subset mean is
    below ``tau - margin`` px is accepted with it, one at or above ``tau + margin`` is
    rejected, and the rest (or those with fewer than half of the subset's points present) go
    on to the next level, the last to the full sets. The subset mean of a regular subset of a
    dense mesh is within a small fraction of the full mean (the vertices oversample the
    image; the error grows with the mean and with the stride), so the decisions are the
    full-set ones unless a level errs by more than its margin.
    """
    plan = frame_pairs(full, F, cam_a, det_a, cam_b, det_b)  # once for every level
    screens = _gathered_screens(plan, screens, backend)
    S = plan.which.size
    keep = np.zeros(S, dtype=bool)
    mean = np.full(S, np.nan)
    todo = np.arange(S)
    evaluated = 0
    for screen, margin in screens:
        if not todo.size:
            break
        # every point counted: whether half the subset is there does not depend on where an
        # early exit stopped
        sums, used, summed = level_sums(
            plan, screen, todo, tau + margin, symmetric, early_exit, backend, precision, True
        )
        evaluated += int(summed.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            m = sums / used
        n = next(iter(screen.values())).n
        enough = used * 2 >= n
        rejected = enough & ~(sums < (tau + margin) * used)  # partial sums: early exit
        accepted = enough & ~rejected & (m < tau - margin)
        keep[todo[accepted]] = True
        mean[todo[accepted]] = m[accepted]
        todo = todo[~(accepted | rejected)]
    if todo.size:
        sums, used, _ = level_sums(plan, full, todo, tau, symmetric, early_exit, backend, precision, False)
        evaluated += int(used.sum())
        ok = sums < tau * used
        keep[todo] = ok
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[todo[ok]] = sums[ok] / used[ok]
    return keep, np.where(keep, mean, np.nan), evaluated


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the screening kernels now (the gather of
    a subset read in runs, the preparing pass's scan and copies). No-op without numba."""
    if not have_numba():
        return
    from maem_ros.core.association.gates.epipolar import epipolar_sums

    F = np.eye(3)[[1, 0, 2]]
    one = np.zeros(1, dtype=np.int64)
    for dtype in (np.float32, np.float64):
        screen = screen_rows(np.ones((1, BLOCK, 2), dtype=dtype), 2)
        if screen is None:
            raise RuntimeError(
                f"screening warmup: a BLOCK ({BLOCK}) of points makes no "
                "screen at stride 2 (SCREEN_MIN_POINTS too high)"
            )
        epipolar_sums(screen, screen, F, one, one, 1.0, True, True, "numba", "mixed")
    screen_copies(np.ones((1, BLOCK, 2), dtype=np.float32), (2, 4))
