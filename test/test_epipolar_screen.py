"""The screened mesh gate: pairs are decided on a fixed 1/stride subset of the vertices (runs of
SCREEN_RUN consecutive ones) unless their subset mean is within the margin of tau, where the
next level (a finer subset, last the full set) decides; screen_stride 1 is the paper's gate over
every vertex."""
from __future__ import annotations

import dataclasses
import gc
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from maem_ros.core.association import AssociationParams, ExecutionParams, PairGates, associate
from maem_ros.core.association.gates import epipolar, screening
from maem_ros.core.association.gates.epipolar_constants import RSQRT_ERR
from maem_ros.core.detections import DetectionTable, FrameDetections

#: a rectified pair (b = a shifted along x): epipolar lines are image rows, so a vertex's
#: (symmetric and forward) distance is exactly its row offset |v_b - v_a|
F_ROWS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
N = 4096
STRIDE = 8
TAU = 8.0
MARGIN = 1.0
#: relative tolerance of an accepted mean (numba "mixed": the 1/sqrt estimate's bound; every
#: vertex here sits at one distance, so its error does not average out over the points)
MEAN_REL = RSQRT_ERR
#: a coarser screening level before the screen
COARSE = 32
COARSE_MARGIN = 2.5


def _screened_ids(n: int, stride: int) -> np.ndarray:
    """The vertex ids screen_rows keeps: the first SCREEN_RUN of every SCREEN_RUN * stride."""
    k = np.arange(n // (screening.SCREEN_RUN * stride) * screening.SCREEN_RUN * stride)
    return k[k % (screening.SCREEN_RUN * stride) < screening.SCREEN_RUN]


def _pair(on_screen: float, elsewhere: float, seed: int = 0, n: int = N,
          on_coarse: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One detection in a and one in b (n vertices) whose vertices lie on_screen px off their
    epipolar lines on the screened ids (on_coarse px on those of the COARSE subset, if
    given) and elsewhere px off on the others."""
    rng = np.random.default_rng(seed)
    xa = rng.uniform(100, 900, (1, n, 2)).astype(np.float32)
    offset = np.full(n, elsewhere, np.float32)
    offset[_screened_ids(n, STRIDE)] = on_screen
    if on_coarse is not None:
        offset[_screened_ids(n, COARSE)] = on_coarse
    xb = xa.copy()
    xb[0, :, 0] += rng.uniform(-50, 50, n).astype(np.float32)  # along the line: no distance
    xb[0, :, 1] += offset * rng.choice(np.float32([-1, 1]), n)
    return xa, xb


def _gate(xa, xb, stride: int = STRIDE, margin: float = MARGIN):
    screen_a, screen_b = screening.screen_rows(xa, stride), screening.screen_rows(xb, stride)
    screen = None if screen_a is None else (screen_a, screen_b)
    one = np.zeros(1, np.int64)
    return screening.screened_means((epipolar.point_rows(xa), epipolar.point_rows(xb)), screen,
                                   F_ROWS, one, one, TAU, margin)


def _full_mean(on_screen: float, elsewhere: float) -> float:
    s = _screened_ids(N, STRIDE).size
    return (on_screen * s + elsewhere * (N - s)) / N


def test_screen_rows_keeps_runs_of_consecutive_points_one_in_every_stride():
    x = np.arange(2 * N, dtype=np.float32).reshape(1, N, 2)
    rows = screening.screen_rows(x, STRIDE)
    ids = _screened_ids(N, STRIDE)
    np.testing.assert_array_equal(rows.points(0), x[0, ids])
    assert np.shares_memory(rows.flat, x)  # described in place, not copied
    assert rows.n == N // STRIDE
    assert screening.screen_rows(x, 1) is None  # off
    assert screening.screen_rows(x[:, :100], STRIDE) is None  # too few points to screen


def test_a_clear_subset_mean_decides_and_is_the_pairs_distance():
    keep, mean, evaluated = _gate(*_pair(5.0, 7.9))
    # within the 1/sqrt estimate's bound: x86-64 without AVX-512 estimates to 12 bits, not 14
    assert keep[0] and mean[0] == pytest.approx(5.0, rel=MEAN_REL)
    assert evaluated == N // STRIDE  # the full set was not read
    keep, mean, _ = _gate(*_pair(TAU + MARGIN + 0.5, 1.0))
    assert not keep[0] and np.isnan(mean[0])  # rejected by the subset (full mean ~2 px)


@pytest.mark.parametrize("on_screen, elsewhere", [(7.5, 9.0), (8.5, 7.0), (7.2, 8.1), (8.9, 7.95)])
def test_a_subset_mean_within_the_margin_is_decided_on_the_full_set(on_screen, elsewhere):
    keep, mean, evaluated = _gate(*_pair(on_screen, elsewhere))
    full = _full_mean(on_screen, elsewhere)
    assert keep[0] == (full < TAU)
    if keep[0]:
        assert mean[0] == pytest.approx(full, rel=MEAN_REL)
    assert evaluated > N // STRIDE


def test_a_subset_rejected_by_an_early_exit_before_half_its_points_is_not_read_again():
    """A far pair's screen stops after its first block, having summed fewer than half of the
    subset's points: the points it did not reach are still there (counted, not summed), so the
    screen decides it, as it would without the early exit, and the full set is not read."""
    n = 3 * epipolar.BLOCK * STRIDE  # a subset of three blocks: the first is under half of it
    xa, xb = _pair(100.0, 1.0, n=n)
    screen = screening.screen_rows(xa, STRIDE).n
    assert 2 * np.diff(epipolar.block_order(screen)[0]) < screen
    for backend in epipolar.BACKENDS:
        screen_a, screen_b = screening.screen_rows(xa, STRIDE), screening.screen_rows(xb, STRIDE)
        one = np.zeros(1, np.int64)
        keep, mean, evaluated = screening.screened_means(
            (epipolar.point_rows(xa), epipolar.point_rows(xb)), (screen_a, screen_b), F_ROWS,
            one, one, TAU, MARGIN, backend=backend)
        assert not keep[0] and np.isnan(mean[0])
        assert evaluated == np.diff(epipolar.block_order(screen)[0])[0], backend


def test_screens_in_threads_at_once_give_what_they_give_one_after_the_other():
    """The screens' gathered points live in per-thread scratch memory kept between calls
    (grown as needed): threads running at once (the kernels release the GIL) and calls of
    other sizes in between do not disturb each other's points."""
    jobs = [_pair(7.0 + 0.25 * k, 7.5, seed=k, n=N * (1 + k % 3)) for k in range(8)]
    alone = [_gate(*job) for job in jobs]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda job: _gate(*job), jobs * 8))
    for k, got in enumerate(together):
        want = alone[k % len(jobs)]
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert got[2] == want[2]


def test_without_a_screen_every_pair_is_decided_on_the_full_set():
    for on_screen, elsewhere in [(5.0, 7.9), (9.5, 1.0)]:
        keep, mean, evaluated = _gate(*_pair(on_screen, elsewhere), stride=1)
        full = _full_mean(on_screen, elsewhere)
        assert keep[0] == (full < TAU) and evaluated == N
        assert mean[0] == pytest.approx(full, rel=MEAN_REL)


def test_a_subset_with_most_points_missing_defers_to_the_full_set():
    xa, xb = _pair(9.5, 1.0)  # the subset alone would reject
    xa[0, _screened_ids(N, STRIDE)[::3]] = np.nan  # a third missing in a ...
    xb[0, _screened_ids(N, STRIDE)[1::3], 1] = np.nan  # ... another third in b
    keep, mean, _ = _gate(xa, xb)
    assert keep[0]  # the full set's mean is ~1.3 px (the missing ones take no part)
    assert 1.0 < mean[0] < TAU


def _two_levels(xa, xb):
    """The gate with the coarse level and the screen (as the association's default)."""
    rows = [(screening.screen_rows(xa, k), screening.screen_rows(xb, k)) for k in (COARSE, STRIDE)]
    one = np.zeros(1, np.int64)
    return screening.frame_screened_means(
        {0: epipolar.point_rows(xa), 1: epipolar.point_rows(xb)},
        [(dict(enumerate(r)), m) for r, m in zip(rows, (COARSE_MARGIN, MARGIN))], {(0, 1): F_ROWS},
        one, one, one + 1, one, TAU)


def test_screen_levels_decide_coarse_to_fine_each_within_its_margin():
    coarse, fine = N // COARSE, N // STRIDE
    # clear on the coarse subset: decided there, with its mean (the rest is never read)
    keep, mean, evaluated = _two_levels(*_pair(7.9, 7.9, on_coarse=2.0))
    assert keep[0] and mean[0] == pytest.approx(2.0, rel=MEAN_REL) and evaluated == coarse
    keep, mean, evaluated = _two_levels(*_pair(1.0, 1.0, on_coarse=TAU + COARSE_MARGIN + 0.5))
    assert not keep[0] and np.isnan(mean[0]) and evaluated == coarse
    # within the coarse margin, clear on the screen: the screen decides
    keep, mean, evaluated = _two_levels(*_pair(3.0, 9.0, on_coarse=TAU + 1.5))
    screen_mean = (3.0 * (fine - coarse) + (TAU + 1.5) * coarse) / fine
    assert keep[0] and mean[0] == pytest.approx(screen_mean, rel=MEAN_REL)
    assert evaluated == coarse + fine
    # within both margins: the full set decides
    for on_screen, elsewhere in [(7.5, 9.0), (8.5, 7.0)]:
        keep, mean, evaluated = _two_levels(*_pair(on_screen, elsewhere, on_coarse=on_screen))
        assert keep[0] == (_full_mean(on_screen, elsewhere) < TAU)
        assert evaluated == coarse + fine + N


def test_the_two_levels_gathered_in_one_pass_give_what_each_level_gathered_gives():
    """The coarse level's runs are every (COARSE // STRIDE)-th run of the screen's: the numba
    path copies both subsets in one pass over the points. With the coarse subset described
    over another view of the memory (so each level gathers its own), every result is the
    same, bit for bit; the numpy reference decides the same."""
    cases = [(7.5, 9.0, 7.5), (3.0, 9.0, TAU + 1.5), (7.9, 7.9, 2.0), (8.5, 7.0, 8.5),
             (1.0, 1.0, TAU + 3.0)]
    pairs = [_pair(s, e, seed=k, on_coarse=c) for k, (s, e, c) in enumerate(cases)]
    xa = np.concatenate([a for a, _ in pairs])
    xb = np.concatenate([b for _, b in pairs])
    every = np.arange(len(cases))
    ia, jb = np.repeat(every, len(cases)), np.tile(every, len(cases))
    full = {0: epipolar.point_rows(xa), 1: epipolar.point_rows(xb)}

    def levels(apart: bool):
        out = []
        for k, m in ((COARSE, COARSE_MARGIN), (STRIDE, MARGIN)):
            rows = {c: screening.screen_rows(full[c], k) for c in full}
            if apart and k == COARSE:
                rows = {c: dataclasses.replace(r, flat=r.flat.view()) for c, r in rows.items()}
            out.append((rows, m))
        return out

    def gate(apart: bool, backend: str = "auto"):
        return screening.frame_screened_means(full, levels(apart), {(0, 1): F_ROWS}, 0 * ia, ia,
                                             0 * ia + 1, jb, TAU, backend=backend)

    if epipolar.have_numba():  # the one pass runs: both levels come back contiguous
        plan = epipolar.frame_pairs(full, {(0, 1): F_ROWS}, 0 * ia, ia, 0 * ia + 1, jb)
        for apart, runs in ((False, {0}), (True, {screening.SCREEN_RUN})):
            got = screening._gathered_screens(plan, levels(apart), "auto")
            assert {r.run for level, _ in got for r in level.values()} == runs
    fused, apart = gate(False), gate(True)
    for got, want in zip(fused, apart):
        np.testing.assert_array_equal(got, want)
    # the detections' own pairs: full set (mean 8.8), screen (4.6), coarse level (2.0), full
    # set (7.2), coarse level (11)
    assert fused[0][::len(cases) + 1].tolist() == [False, True, True, True, False]
    np.testing.assert_array_equal(gate(False, "numpy")[0], fused[0])


def _block_ranges(x: np.ndarray) -> np.ndarray:
    """Reference of PointRows.ranges: per detection and BLOCK-point block (natural order),
    (min, max) over both coordinates, (inf, -inf) where one is NaN or inf."""
    N, n = x.shape[:2]
    out = np.empty((N, -(-n // epipolar.BLOCK), 2), np.float32)
    for b, start in enumerate(range(0, n, epipolar.BLOCK)):
        part = x[:, start:start + epipolar.BLOCK].reshape(N, -1)
        bad = ~np.isfinite(part).all(axis=1)
        out[:, b, 0] = np.where(bad, np.inf, part.min(axis=1))
        out[:, b, 1] = np.where(bad, -np.inf, part.max(axis=1))
    return out


@pytest.mark.parametrize("strides", [(8, 32), (8,), (32, 8, 2), (8, 12), (1, 8)])
def test_screen_copies_hold_each_screens_points_the_block_ranges_and_the_first_inf(strides):
    """screen_copies: every stride's screening subset (nested in the finest or not) as
    screen_rows reads it, NaN kept, read-only; each detection's block ranges (with numba);
    the first detection with an inf coordinate, also in a block with a NaN; the extremes of
    the coordinates present."""
    rng = np.random.default_rng(len(strides))
    x = rng.uniform(-100, 2000, (5, 2 * epipolar.BLOCK + 1001, 2)).astype(np.float32)
    x[1, ::7, 0] = np.nan
    x[2, epipolar.BLOCK + 3, 1] = -np.nan
    x[1, 8, 1] = -150.5  # the smallest, in a detection whose blocks all hold a NaN
    copies, ranges, first_inf, extremes = screening.screen_copies(x, strides)
    assert first_inf == -1 and sorted(copies) == sorted(s for s in strides if s > 1)
    assert extremes == (-150.5, float(np.nanmax(x)))
    for stride, got in copies.items():
        screen = screening.screen_rows(x, stride)
        np.testing.assert_array_equal(got, screen._gather(screen.rows))
        assert not got.flags.writeable
    if epipolar.have_numba():  # the full set's and the copies made in the pass
        np.testing.assert_array_equal(ranges[1], _block_ranges(x))
        assert np.isinf(ranges[1][2, 1]).all() and np.isfinite(ranges[1][2, [0, 2]]).all()
        finest = min(s for s in strides if s > 1)
        assert {1, finest} <= set(ranges) <= {1} | set(copies)
        for stride, got in ranges.items():
            np.testing.assert_array_equal(got, _block_ranges(x if stride == 1 else copies[stride]))
            assert not got.flags.writeable
    else:
        assert ranges == {}
    x[3, 2000, 1], x[4, 5, 0] = -np.inf, np.inf
    assert screening.screen_copies(x, strides).first_inf == 3
    assert np.isnan(screening.screen_copies(x, strides).extremes).all()
    x[3, 2000, 1] = 0.0
    x[4, 0, 1] = np.nan  # the inf shares its block with a NaN
    assert screening.screen_copies(x, strides).first_inf == 4


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 3 * epipolar.BLOCK),
    dets=st.integers(1, 4),
    missing=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_screen_copies_extremes_are_those_of_the_coordinates_present(n, dets, missing, seed):
    """The pass's extremes (what a receiver checks pixel limits with instead of reducing the
    vertices again) equal nanmin / nanmax, whatever the blocks' NaN; NaN when none is present."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3000, 5000, (dets, n, 2)).astype(np.float32)
    x[rng.random(x.shape) < missing] = np.nan
    low, high = screening.screen_copies(x, (8, 32)).extremes
    if np.isnan(x).all():
        assert np.isnan(low) and np.isnan(high)
    else:
        assert (low, high) == (float(np.nanmin(x)), float(np.nanmax(x)))


@pytest.mark.skipif(not epipolar.have_numba(), reason="block ranges are the numba kernel's")
def test_the_kernel_given_block_ranges_sums_what_it_sums_computing_them():
    """Full sets with the decoder's block ranges (PointRows.ranges) or without: the same sums
    and counts, bit for bit, over pairs with missing points and pairs near tau; the kernel
    reads them (blocks marked non-finite take the float64 path); ranges that do not describe
    the points are refused."""
    rng = np.random.default_rng(5)
    n = 2 * epipolar.BLOCK + 700
    a = rng.uniform(100, 1500, (6, n, 2)).astype(np.float32)
    b = a + rng.normal(0, 1, (6, 1, 1)).astype(np.float32)
    b[..., 1] += rng.uniform(0, 2 * TAU, (6, 1)).astype(np.float32)  # row offsets: F_ROWS
    a[2, 5000:5010] = np.nan
    given = [epipolar.point_rows(x, screening.screen_copies(x, (8,)).block_ranges[1])
             for x in (a, b)]
    assert all(r.ranges is not None for r in given)
    ia, jb = np.repeat(np.arange(6), 6), np.tile(np.arange(6), 6)
    for early_exit in (True, False):
        got = epipolar.frame_sums(dict(enumerate(given)), {(0, 1): F_ROWS}, 0 * ia, ia,
                                  0 * ia + 1, jb, TAU, early_exit=early_exit)
        want = epipolar.frame_sums({0: a, 1: b}, {(0, 1): F_ROWS}, 0 * ia, ia, 0 * ia + 1, jb,
                                   TAU, early_exit=early_exit)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
    # the kernel reads the given ranges: blocks marked non-finite are summed in float64
    marked = np.empty_like(given[0].ranges)
    marked[..., 0], marked[..., 1] = np.inf, -np.inf
    rows = {0: dataclasses.replace(given[0], ranges=marked), 1: given[1]}
    sums64, used64 = epipolar.frame_sums(rows, {(0, 1): F_ROWS}, 0 * ia, ia, 0 * ia + 1, jb,
                                         TAU, early_exit=False)
    np.testing.assert_array_equal(used64, got[1])
    assert not np.array_equal(sums64, got[0])
    np.testing.assert_allclose(sums64, got[0], rtol=MEAN_REL)
    with pytest.raises(ValueError, match="block ranges .* do not describe"):
        epipolar.point_rows(a[:, :epipolar.BLOCK], given[0].ranges)


def _decoded(scene, f, gates=None):
    """Frame f of the scene decoded from its wire messages (as the association node receives
    them), each prepared by ``gates`` when given."""
    from maem_ros.ros import wire
    frames = {c: wire.msg_to_detections(wire.detections_to_msg(scene.detections(c, f)), "/d")
              for c in scene.rig.names}
    return frames if gates is None else {c: gates.prepare(fd) for c, fd in frames.items()}


def test_prepared_frames_are_gated_exactly_as_unprepared_ones(scene):
    """Frames prepared by the gates (the association node's path: PairGates.prepare as each
    message is decoded) give the gate contiguous subsets (no gather of its own) and block
    ranges, and every decision and mean is the one it gives when it gathers the subsets and
    scans the blocks itself, bit for bit; a selection of a prepared frame (PairGates.select)
    keeps its rows'."""
    params = AssociationParams(k_min=2)
    gates = PairGates(scene.rig, params)
    prepares = gates.execution.backend != "numpy" and epipolar.have_numba()
    for f in (0, scene.config.frames // 2):
        plain, prepared = _decoded(scene, f), _decoded(scene, f, gates)
        assert all(gates.is_prepared(fd) == prepares for fd in prepared.values())
        assert not any(gates.is_prepared(fd) for fd in plain.values())
        by_index = {k: prepared[c] for k, c in enumerate(scene.rig.names)}
        runs = {rows.run for k in by_index for rows in gates.frame_set(by_index).points(k)[1]
                if rows is not None}
        assert runs == ({0} if prepares else {screening.SCREEN_RUN})
        a = associate(scene.rig, plain, params)
        b = associate(scene.rig, prepared, params, gates)
        assert [c.members.tolist() for c in a.clusters] == [c.members.tolist() for c in b.clusters]
        for got, want in zip(_gate_decisions(scene, prepared, gates),
                             _gate_decisions(scene, plain, gates)):
            np.testing.assert_array_equal(got, want)
    if prepares:
        fd = prepared[scene.rig.names[0]]
        keep = np.array([0, fd.n - 1])
        part = gates.select(fd, keep)
        assert gates.is_prepared(part)
        (full, subsets), (part_full, part_subsets) = (gates.camera_points(x, None)
                                                      for x in (fd, part))
        assert full.ranges is not None
        np.testing.assert_array_equal(part_full.ranges, full.ranges[keep])
        assert any(rows is not None for rows in subsets)
        for whole, rows in zip(subsets, part_subsets):
            if whole is None:  # too few vertices for this level
                assert rows is None
                continue
            assert whole.ranges is not None and rows.run == 0
            for k, i in enumerate(keep.tolist()):
                np.testing.assert_array_equal(rows.points(k), whole.points(i))
            np.testing.assert_array_equal(rows.ranges, whole.ranges[keep])
        fd.verts2d = fd.verts2d.copy()  # new vertices: what was prepared no longer describes them
        assert not gates.is_prepared(fd)
        assert gates.camera_points(fd, None)[0].ranges is None


def test_prepared_frames_are_dropped_with_the_frames(scene):
    """The gates keep a frame's prepared data only while the frame lives: a collected frame's
    entry goes (a new object at its address is never mistaken for it)."""
    gates = PairGates(scene.rig, AssociationParams())
    if not gates.prepare_strides():
        pytest.skip("nothing to prepare without numba")
    frames = _decoded(scene, 0, gates)
    assert gates.prepared_frames == len(frames)
    first = scene.rig.names[0]
    del frames[first]
    gc.collect()
    assert gates.prepared_frames == len(frames)
    frames.clear()
    gc.collect()
    assert gates.prepared_frames == 0


def _gate_decisions(scene, frames, gates):
    """(stage, mean) of the pair gates on every cross-camera pair of the frame set."""
    by_index = {k: frames[c] for k, c in enumerate(scene.rig.names)}
    table = DetectionTable.build(by_index, len(scene.rig.names))
    i, j = np.triu_indices(len(table), 1)
    other = table.cam[i] != table.cam[j]
    i, j = i[other], j[other]
    decided = gates.frame_set(by_index).decide(table.cam[i], table.det[i], table.cam[j],
                                               table.det[j])
    return decided.stage, decided.epi


def test_screen_levels_follow_the_params():
    params = ExecutionParams()
    assert params.screen_levels() == [(params.screen_coarse_stride, params.screen_coarse_margin),
                                      (params.screen_stride, params.screen_margin)]
    assert ExecutionParams(screen_coarse_stride=1).screen_levels() == [
        (params.screen_stride, params.screen_margin)]
    assert ExecutionParams(screen_stride=1).screen_levels() == []  # the paper: every vertex
    with pytest.raises(ValueError, match="^screen_coarse_stride: must be 1 .* coarser"):
        ExecutionParams(screen_coarse_stride=params.screen_stride)
    assert AssociationParams().execution == params


def test_screened_and_full_mesh_association_give_the_same_clusters(scene):
    params = AssociationParams(k_min=2)
    assert params.execution.screen_stride > 1  # the default screens
    full = params.replaced({"screen_stride": 1})
    for f in range(0, scene.config.frames, max(1, scene.config.frames // 4)):
        frames = {c: scene.detections(c, f) for c in scene.rig.names}
        fast, exact = associate(scene.rig, frames, params), associate(scene.rig, frames, full)
        assert ([c.members.tolist() for c in fast.clusters]
                == [c.members.tolist() for c in exact.clusters])
        assert fast.stats["epipolar_points_fraction"] < exact.stats["epipolar_points_fraction"]


@pytest.mark.parametrize("layout", ["f32", "q4"])
def test_prepare_keeps_the_subsets_and_block_ranges_the_mesh_gate_reads(scene, layout):
    """PairGates.prepare on a decoded frame: each screening level's subset copied contiguous
    (the points screen_rows reads, NaN kept) with its block ranges, and the full set's block
    ranges (with numba); a level with too few points has none; nothing kept on the frame."""
    from maem_ros.ros import wire
    rng = np.random.default_rng(3)
    n, v = 3, 2000
    xy = rng.uniform(0, 1000, (n, 2))
    verts = rng.uniform(-50, 1500, (n, v, 2)).astype(np.float32)
    verts[1, 7] = np.nan
    dets = FrameDetections("cam0", 1, np.concatenate([xy, xy + 100], 1), np.ones(n),
                           rng.uniform(0, 1000, (n, 5, 2)), rng.normal(0, 1, (n, 5, 3)), verts)
    got = wire.msg_to_detections(wire.detections_to_msg(dets, layout), "/d")
    gates = PairGates(scene.rig, AssociationParams())
    fields = {k: v for k, v in vars(got).items()}
    assert gates.prepare(got) is got
    assert vars(got).keys() == fields.keys() and all(vars(got)[k] is v for k, v in fields.items())
    full, (coarse, fine) = gates.camera_points(got, None)
    assert coarse is None  # 2000 vertices: too few for a 1/32 screen
    screen = screening.screen_rows(got.verts2d, 8)
    want = screen._gather(screen.rows)
    for i in range(n):
        np.testing.assert_array_equal(fine.points(i), want[i])
    assert np.isnan(fine.points(1)[7]).all()  # vertex 7: the last of detection 1's first run
    if not gates.prepare_strides():
        assert not gates.is_prepared(got) and full.ranges is None and fine.run
        return
    assert gates.is_prepared(got) and fine.run == 0
    finite = np.array([0, 2])
    np.testing.assert_array_equal(fine.ranges[finite, 0, 1], want[finite].max(axis=(1, 2)))
    assert fine.ranges[1, 0].tolist() == [np.inf, -np.inf]  # a NaN in its copy
    np.testing.assert_array_equal(full.ranges[finite, 0, 0], got.verts2d[finite].min(axis=(1, 2)))
    np.testing.assert_array_equal(full.ranges[finite, 0, 1], got.verts2d[finite].max(axis=(1, 2)))
    assert full.ranges.shape == (3, 1, 2) and full.ranges[1, 0].tolist() == [np.inf, -np.inf]


@pytest.mark.parametrize("verify", ["mesh", "sparse"])
def test_the_track_stage_decides_pairs_with_the_associations_gates(scene, verify):
    """The association (candidates: enumeration and reprojection gate in one pass, then
    decide_rows) and the track stage (decide on arbitrary pairs, the reprojection gate run
    there) are the same gates: the same stage and mean for every pair, bit for bit; the track
    stage's gates differ only in their epipolar mode and read the frames the association's
    prepared."""
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    params = AssociationParams(k_min=2)
    stage = TemporalAssociator(scene.rig, params, TemporalParams(verify_epipolar=verify))
    assert stage.verify_gates.epipolar_gate == verify
    frames = _decoded(scene, 1, stage.gates)
    by_index = {k: frames[c] for k, c in enumerate(scene.rig.names)}
    assert all(stage.verify_gates.is_prepared(fd) == bool(stage.gates.prepare_strides())
               for fd in by_index.values())
    table = DetectionTable.build(by_index, len(scene.rig))
    gates = stage.gates.with_epipolar_gate(verify)
    i, j, ok = gates.candidates(table)
    rows = gates.frame_set(by_index).decide_rows(table, i, j, ok)
    pairs = stage.verify_gates.frame_set(by_index).decide(table.cam[i], table.det[i],
                                                          table.cam[j], table.det[j])
    np.testing.assert_array_equal(rows.stage, pairs.stage)
    np.testing.assert_array_equal(rows.epi, pairs.epi)
    assert (rows.stage == 0).any() and (rows.stage == 1).any()
