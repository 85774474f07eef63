"""The screened mesh gate: pairs are decided on a fixed 1/stride subset of the vertices (runs of
SCREEN_RUN consecutive ones) unless their subset mean is within the margin of tau, where the
next level (a finer subset, last the full set) decides; screen_stride 1 is the paper's gate over
every vertex."""
from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from maem_ros.core.association.gates import epipolar
from maem_ros.core.association.pipeline import AssociationParams, associate

#: a rectified pair (b = a shifted along x): epipolar lines are image rows, so a vertex's
#: (symmetric and forward) distance is exactly its row offset |v_b - v_a|
F_ROWS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
N = 4096
STRIDE = 8
TAU = 8.0
MARGIN = 1.0
#: relative tolerance of an accepted mean (numba "mixed": the 1/sqrt estimate's bound; every
#: vertex here sits at one distance, so its error does not average out over the points)
MEAN_REL = epipolar._RSQRT_ERR
#: a coarser screening level before the screen
COARSE = 32
COARSE_MARGIN = 2.5


def _screened_ids(n: int, stride: int) -> np.ndarray:
    """The vertex ids screen_rows keeps: the first SCREEN_RUN of every SCREEN_RUN * stride."""
    k = np.arange(n // (epipolar.SCREEN_RUN * stride) * epipolar.SCREEN_RUN * stride)
    return k[k % (epipolar.SCREEN_RUN * stride) < epipolar.SCREEN_RUN]


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
    screen_a, screen_b = epipolar.screen_rows(xa, stride), epipolar.screen_rows(xb, stride)
    screen = None if screen_a is None else (screen_a, screen_b)
    one = np.zeros(1, np.int64)
    return epipolar.screened_means((epipolar.point_rows(xa), epipolar.point_rows(xb)), screen,
                                   F_ROWS, one, one, TAU, margin)


def _full_mean(on_screen: float, elsewhere: float) -> float:
    s = _screened_ids(N, STRIDE).size
    return (on_screen * s + elsewhere * (N - s)) / N


def test_screen_rows_keeps_runs_of_consecutive_points_one_in_every_stride():
    x = np.arange(2 * N, dtype=np.float32).reshape(1, N, 2)
    rows = epipolar.screen_rows(x, STRIDE)
    ids = _screened_ids(N, STRIDE)
    np.testing.assert_array_equal(rows.points(0), x[0, ids])
    assert np.shares_memory(rows.flat, x)  # described in place, not copied
    assert rows.n == N // STRIDE
    assert epipolar.screen_rows(x, 1) is None  # off
    assert epipolar.screen_rows(x[:, :100], STRIDE) is None  # too few points to screen


def test_a_clear_subset_mean_decides_and_is_the_pairs_distance():
    keep, mean, evaluated = _gate(*_pair(5.0, 7.9))
    assert keep[0] and mean[0] == pytest.approx(5.0, abs=1e-4)
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
    screen = epipolar.screen_rows(xa, STRIDE).n
    assert 2 * np.diff(epipolar.block_order(screen)[0]) < screen
    for backend in epipolar.BACKENDS:
        screen_a, screen_b = epipolar.screen_rows(xa, STRIDE), epipolar.screen_rows(xb, STRIDE)
        one = np.zeros(1, np.int64)
        keep, mean, evaluated = epipolar.screened_means(
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
    rows = [(epipolar.screen_rows(xa, k), epipolar.screen_rows(xb, k)) for k in (COARSE, STRIDE)]
    one = np.zeros(1, np.int64)
    return epipolar.frame_screened_means(
        {0: epipolar.point_rows(xa), 1: epipolar.point_rows(xb)},
        [(dict(enumerate(r)), m) for r, m in zip(rows, (COARSE_MARGIN, MARGIN))], {(0, 1): F_ROWS},
        one, one, one + 1, one, TAU)


def test_screen_levels_decide_coarse_to_fine_each_within_its_margin():
    coarse, fine = N // COARSE, N // STRIDE
    # clear on the coarse subset: decided there, with its mean (the rest is never read)
    keep, mean, evaluated = _two_levels(*_pair(7.9, 7.9, on_coarse=2.0))
    assert keep[0] and mean[0] == pytest.approx(2.0, abs=1e-4) and evaluated == coarse
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
            rows = {c: epipolar.screen_rows(full[c], k) for c in full}
            if apart and k == COARSE:
                rows = {c: dataclasses.replace(r, flat=r.flat.view()) for c, r in rows.items()}
            out.append((rows, m))
        return out

    def gate(apart: bool, backend: str = "auto"):
        return epipolar.frame_screened_means(full, levels(apart), {(0, 1): F_ROWS}, 0 * ia, ia,
                                             0 * ia + 1, jb, TAU, backend=backend)

    if epipolar.have_numba():  # the one pass runs: both levels come back contiguous
        plan = epipolar._frame_pairs(full, {(0, 1): F_ROWS}, 0 * ia, ia, 0 * ia + 1, jb)
        for apart, runs in ((False, {0}), (True, {epipolar.SCREEN_RUN})):
            got = epipolar._gathered_screens(plan, levels(apart), "auto")
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
    the first detection with an inf coordinate, also in a block with a NaN."""
    rng = np.random.default_rng(len(strides))
    x = rng.uniform(-100, 2000, (5, 2 * epipolar.BLOCK + 1001, 2)).astype(np.float32)
    x[1, ::7, 0] = np.nan
    x[2, epipolar.BLOCK + 3, 1] = -np.nan
    copies, ranges, first_inf = epipolar.screen_copies(x, strides)
    assert first_inf == -1 and sorted(copies) == sorted(s for s in strides if s > 1)
    for stride, got in copies.items():
        screen = epipolar.screen_rows(x, stride)
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
    assert epipolar.screen_copies(x, strides).first_inf == 3
    x[3, 2000, 1] = 0.0
    x[4, 0, 1] = np.nan  # the inf shares its block with a NaN
    assert epipolar.screen_copies(x, strides).first_inf == 4


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
    given = [epipolar.point_rows(x, epipolar.screen_copies(x, (8,)).block_ranges[1])
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
    np.testing.assert_allclose(sums64, got[0], rtol=1e-5)
    with pytest.raises(ValueError, match="block ranges .* do not describe"):
        epipolar.point_rows(a[:, :epipolar.BLOCK], given[0].ranges)


def test_decoded_screen_copies_give_the_gate_what_it_gathers_itself(scene):
    """Detections decoded with the gate's screening subsets copied (the association node's
    path): the gate reads the copies (no gather of its own) and the block ranges, and every
    decision and mean is the one it gives when it gathers the subsets and scans the blocks
    itself, bit for bit; a detections subset (select) keeps its rows' copies and ranges."""
    from maem_ros.core.association import pipeline as association
    from maem_ros.ros import wire
    params = AssociationParams(k_min=2)
    strides = association.decode_screen_strides(params)
    assert strides == (params.screen_coarse_stride, params.screen_stride) or \
        not epipolar.have_numba()
    for f in (0, scene.config.frames // 2):
        msgs = {c: wire.detections_to_msg(scene.detections(c, f)) for c in scene.rig.names}
        plain, copied = ({c: wire.msg_to_detections(m, "/d", screen_strides=s)
                          for c, m in msgs.items()} for s in ((), strides))
        runs = {rows.run for _, subsets in association._gate_points(
            {k: copied[c] for k, c in enumerate(scene.rig.names)}, params).values()
            for rows in subsets if rows is not None}
        assert runs == ({0} if strides else {epipolar.SCREEN_RUN})
        a, b = associate(scene.rig, plain, params), associate(scene.rig, copied, params)
        assert [c.members.tolist() for c in a.clusters] == [c.members.tolist() for c in b.clusters]
        for got, want in zip(_gate_means(scene, copied, params), _gate_means(scene, plain, params)):
            np.testing.assert_array_equal(got, want)
    if strides:
        fd = copied[scene.rig.names[0]]
        keep = np.array([0, fd.n - 1])
        np.testing.assert_array_equal(fd.select(keep).screen_copy(strides[-1]),
                                      fd.screen_copy(strides[-1])[keep])
        copied_strides = [s for s in strides if fd.screen_copy(s) is not None]
        assert copied_strides
        for stride in [1] + copied_strides:
            np.testing.assert_array_equal(fd.select(keep).block_ranges(stride),
                                          fd.block_ranges(stride)[keep])
        full, subsets = association._gate_points({0: fd}, params)[0]
        # the kernel is given them
        assert full.ranges is fd.block_ranges() is not None
        assert all(r.ranges is fd.block_ranges(s) is not None
                   for r, s in zip(subsets, strides) if s in copied_strides)
        fd.verts2d = fd.verts2d.copy()  # new vertices: the copies no longer describe them
        assert fd.screen_copy(strides[-1]) is None and fd.block_ranges() is None


def _gate_means(scene, frames, params):
    """(keep, mean) of the mesh gate on every cross-camera pair of the frame set."""
    from maem_ros.core.association import pipeline as association
    from maem_ros.core.detections import DetectionTable
    by_index = {k: frames[c] for k, c in enumerate(scene.rig.names)}
    table = DetectionTable.build(by_index, len(scene.rig.names))
    i, j = np.triu_indices(len(table), 1)
    other = table.cam[i] != table.cam[j]
    F = association._rig_cache(scene.rig).pairs
    return association._epipolar_gate(table, i[other], j[other], F, params,
                                      {"epipolar_points_fraction": 0.0})


def test_screen_levels_follow_the_params():
    params = AssociationParams()
    assert params.screen_levels() == [(params.screen_coarse_stride, params.screen_coarse_margin),
                                      (params.screen_stride, params.screen_margin)]
    assert AssociationParams(screen_coarse_stride=1).screen_levels() == [
        (params.screen_stride, params.screen_margin)]
    assert AssociationParams(screen_stride=1).screen_levels() == []  # the paper: every vertex
    with pytest.raises(ValueError, match="^screen_coarse_stride: must be 1 .* coarser"):
        AssociationParams(screen_coarse_stride=params.screen_stride)


def test_screened_and_full_mesh_association_give_the_same_clusters(scene):
    params = AssociationParams(k_min=2)
    assert params.screen_stride > 1  # the default screens
    full = dataclasses.replace(params, screen_stride=1)
    for f in range(0, scene.config.frames, max(1, scene.config.frames // 4)):
        frames = {c: scene.detections(c, f) for c in scene.rig.names}
        fast, exact = associate(scene.rig, frames, params), associate(scene.rig, frames, full)
        assert ([c.members.tolist() for c in fast.clusters]
                == [c.members.tolist() for c in exact.clusters])
        assert fast.stats["epipolar_points_fraction"] < exact.stats["epipolar_points_fraction"]
