"""The epipolar kernel: the numba kernel (every camera pair of a frame in one call, a
detection's lines shared by its pairs, points read in place) decides exactly like the numpy
reference and the plain full mean, with missing points, shared detections, strided message
views, early exit and points at the epipole."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from maem_ros.core.association.gates import epipolar, screening
from maem_ros.core.geometry.camera import fundamental_matrix
from helpers_scene import ring_rig, two_facing_cameras
from test_association import VARIANTS

BACKENDS = ["numpy"] + (["numba"] if epipolar.have_numba() else [])


def _scene(seed: int, n: int, tau: float, na: int, nb: int):
    """na detections in a, nb in b; b's detection d sees a's detection d % na's points moved off
    their epipolar lines by amounts around tau (some pairs just below / above it)."""
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (na, n, 3)) + [0, 0, 1]
    xa = rig["a"].project_rectified(X)
    xb = rig["b"].project_rectified(X[np.arange(nb) % na])
    lines = np.einsum("ij,dnj->dni", F, np.concatenate([xa, np.ones((na, n, 1))], -1))
    normal = lines[np.arange(nb) % na, :, :2]
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    shift = rng.uniform(0.0, 2.0, (nb, n, 1)) * rng.uniform(0.5, 1.5, (nb, 1, 1)) * tau
    xb = xb + normal * shift * rng.choice([-1, 1], (nb, n, 1))
    return F, xa, xb, rng


def _full_mean(xa, xb, F, ia, jb, symmetric):
    d = epipolar.point_distances(xa[ia], xb[jb], F, symmetric)
    present = ~np.isnan(d)
    with np.errstate(invalid="ignore"):
        return np.where(present, d, 0.0).sum(axis=1) / present.sum(axis=1), present.sum(axis=1)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 2500), symmetric=st.booleans(),
       tau=st.floats(0.5, 20.0), missing=st.sampled_from([0.0, 0.02, 0.3]),
       dtype=st.sampled_from([np.float32, np.float64]), pairs=st.integers(1, 40))
def test_kernel_decisions_equal_the_reference_and_the_full_mean(seed, n, symmetric, tau, missing,
                                                                dtype, pairs):
    F, xa, xb, rng = _scene(seed, n, tau, 5, 7)
    xa = xa.astype(dtype)
    xb = xb.astype(dtype)
    xa[rng.random(xa.shape[:2]) < missing] = np.nan  # missing vertices (q4 65535)
    xb[rng.random(xb.shape[:2]) < missing, 1] = np.nan  # one coordinate is enough
    # random candidates: detections appear in several pairs (the cached norms are shared)
    ia, jb = rng.integers(0, 5, pairs), rng.integers(0, 7, pairs)
    mean, count = _full_mean(xa, xb, F, ia, jb, symmetric)
    reference = ~(mean < tau)  # no common point (NaN mean) rejects
    near_tie = np.abs(mean - tau) < 1e-9 * tau
    for backend, precision, rtol, atol in VARIANTS:
        for early in (True, False):
            sums, used = epipolar.epipolar_sums(xa, xb, F, ia, jb, tau, symmetric, early, backend,
                                                precision)
            reject = ~(sums < tau * used)
            assert np.array_equal(reject[~near_tie], reference[~near_tie]), (backend, precision)
            assert np.array_equal(used[~reject], count[~reject])  # accepted: summed in full
            np.testing.assert_allclose(sums[~reject] / used[~reject], mean[~reject], rtol=rtol,
                                       atol=atol)
            if not early:
                assert np.array_equal(used, count)
                ok = count > 0
                np.testing.assert_allclose(sums[ok] / used[ok], mean[ok], rtol=rtol, atol=atol)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 3000), symmetric=st.booleans(),
       rel=st.sampled_from([1e-3, 1e-5, 1e-7, 1e-9, 0.0]), above=st.booleans(),
       offset=st.sampled_from([0.0, 1500.0, -700.0]))
@pytest.mark.slow
def test_mixed_precision_decides_like_float64_at_the_threshold(seed, n, symmetric, rel, above,
                                                                offset):
    if not epipolar.have_numba():
        return
    """tau placed within rel of each pair's exact mean (below or above): the float32 sums
    cannot tell, so the error bound must send the pair to float64 and still decide exactly;
    points far from the image origin (offset) test the centring."""
    F, xa, xb, rng = _scene(seed, n, 8.0, 5, 7)
    shift = np.array([offset, -0.5 * offset])
    T = np.array([[1.0, 0, -shift[0]], [0, 1, -shift[1]], [0, 0, 1]])
    F = T.T @ F @ T  # the same geometry for points moved by shift in both images
    xa = (xa + shift).astype(np.float32)
    xb = (xb + shift).astype(np.float32)
    ia, jb = np.arange(5).repeat(7), np.tile(np.arange(7), 5)
    mean, _ = _full_mean(xa, xb, F, ia, jb, symmetric)
    for s in range(ia.size):
        tau = mean[s] * (1 + rel) if above else mean[s] * (1 - rel)
        # with a second pair of the same a-side detection: the two run in one shared loop
        other = ia[s] * 7 + (jb[s] + 1) % 7
        pair = (ia[[s, other]], jb[[s, other]], tau, symmetric)
        # at an exact tie (rel 0) float64 roundings decide: compare with the numba float64 sums
        # the mixed kernel falls back to; otherwise with the numpy reference
        want = epipolar.epipolar_sums(xa, xb, F, *pair, backend="numpy" if rel else "numba",
                                      precision="float64")
        for backend, precision, *_ in VARIANTS[1:]:
            got = epipolar.epipolar_sums(xa, xb, F, *pair, backend=backend, precision=precision)
            assert (got[0][0] < tau * got[1][0]) == (want[0][0] < tau * want[1][0]), \
                (precision, rel)
            got = epipolar.epipolar_sums(xa, xb, F, *(v[:1] for v in pair[:2]), tau, symmetric,
                                         backend=backend, precision=precision)
            assert (got[0][0] < tau * got[1][0]) == (want[0][0] < tau * want[1][0])


def test_mixed_precision_runs_in_float32_and_stays_close():
    """On a well-conditioned scene the float32 path is taken (sums differ from float64) and
    accepted means agree with float64 far inside the bound's 2^-10: the 1/sqrt estimate's
    errors average over the points (~1e-5 relative on 4,000 points)."""
    if not epipolar.have_numba():
        return
    F, xa, xb, _ = _scene(3, 4000, 8.0, 4, 4)
    xa, xb = xa.astype(np.float32), xb.astype(np.float32)
    ia = jb = np.arange(4)
    fast = epipolar.epipolar_sums(xa, xb, F, ia, jb, 1e3, backend="numba", precision="mixed")
    exact = epipolar.epipolar_sums(xa, xb, F, ia, jb, 1e3, backend="numba", precision="float64")
    assert not np.array_equal(fast[0], exact[0])
    np.testing.assert_allclose(fast[0], exact[0], rtol=1e-4)
    assert np.array_equal(fast[1], exact[1])


def test_strided_message_views_are_read_in_place():
    F, xa, xb, _ = _scene(1, 700, 8.0, 3, 3)
    # points inside wider records (as a PointCloud2 field view): (N, n, 2) with a row stride
    rec = np.zeros((3, 2 * 700 + 11), dtype=np.float32)
    rec[:, 5:5 + 1400] = xa.reshape(3, -1)
    view = rec[:, 5:5 + 1400].reshape(3, 700, 2)
    rows = epipolar.point_rows(view)
    assert np.shares_memory(rows.flat, rec)
    ia = jb = np.arange(3)
    for backend in BACKENDS:
        got = epipolar.epipolar_sums(view, xb, F, ia, jb, 8.0, backend=backend)
        ref = epipolar.epipolar_sums(np.ascontiguousarray(view), xb, F, ia, jb, 8.0,
                                     backend=backend)
        for g, r in zip(got, ref):
            np.testing.assert_array_equal(g, r)
    # a layout the kernel cannot read in place (big-endian) is copied once and still right
    big = xa.astype(">f8")
    np.testing.assert_allclose(epipolar.epipolar_sums(big, xb, F, ia, jb, 8.0)[0],
                               epipolar.epipolar_sums(xa, xb, F, ia, jb, 8.0)[0], rtol=1e-12)


def test_wrong_pairs_with_missing_points_exit_early_and_all_missing_rejects():
    """test_association covers the early exit of complete detections; here half of b's points
    are missing, so the exit bound tau * (used + still to come) shrinks as they are walked."""
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    rng = np.random.default_rng(0)
    xa = rng.uniform(0, 1000, (1, 18439, 2)).astype(np.float32)
    xb = rng.uniform(0, 1000, (1, 18439, 2)).astype(np.float32)
    xb[0, ::2] = np.nan
    for backend, precision, *_ in VARIANTS:
        sums, used = epipolar.epipolar_sums(xa, xb, F, [0], [0], 8.0, backend=backend,
                                            precision=precision)
        assert sums[0] >= 8.0 * used[0] and 0 < used[0] <= epipolar.BLOCK
        none = np.full((1, 600, 2), np.nan, np.float32)
        sums, used = epipolar.epipolar_sums(none, xb[:1, :600], F, [0], [0], 8.0, backend=backend)
        assert used[0] == 0 and not sums[0] < 8.0 * used[0]


def test_points_at_the_epipole_reject_in_both_backends():
    """F e_a = 0: the line of a point at a's epipole is undefined (inf / NaN distance)."""
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    X = np.random.default_rng(2).uniform(-1, 1, (1, 1100, 3)) + [0, 0, 1]
    xa, xb = rig["a"].project_rectified(X), rig["b"].project_rectified(X)
    e_a = np.linalg.svd(F)[2][-1]  # a's epipole: F's right null space
    xa_epi = np.tile(e_a[:2] / e_a[2], (1, 1100, 1))
    assert np.abs(F @ e_a).max() < 1e-12
    for backend, precision, *_ in VARIANTS:
        sums, used = epipolar.epipolar_sums(xa, xb, F, [0], [0], 8.0, backend=backend,
                                            precision=precision)
        assert sums[0] < 1e-6 * used[0] and used[0] == 1100  # a perfect pair passes
        for symmetric in (True, False):
            sums, used = epipolar.epipolar_sums(xa_epi, xb, F, [0], [0], 8.0, symmetric,
                                                backend=backend, precision=precision)
            assert not sums[0] < 8.0 * used[0]
    # float32 points (the mixed kernel's input): a few points at (float32-rounded) epipole
    # among correct ones decide like the float64 reference, with and without early exit
    xa32, xb32 = xa.astype(np.float32), xb.astype(np.float32)
    xa32[0, ::97] = e_a[:2] / e_a[2]
    for symmetric in (True, False):
        for early in (True, False):
            want = epipolar.epipolar_sums(xa32, xb32, F, [0], [0], 8.0, symmetric, early, "numpy")
            for backend, precision, *_ in VARIANTS[1:]:
                got = epipolar.epipolar_sums(xa32, xb32, F, [0], [0], 8.0, symmetric, early,
                                             backend, precision)
                assert (got[0] < 8.0 * got[1]) == (want[0] < 8.0 * want[1])


def test_mixed_runs_in_float64_when_the_float32_rsqrt_is_outside_the_bound(monkeypatch):
    """The error bound assumes the compiled float32 1/sqrt is within 2^-10; where the check at
    first use fails, "mixed" must give the float64 sums."""
    if not epipolar.have_numba():
        return
    assert epipolar.rsqrt_within_bound()  # on this machine the float32 path is taken
    F, xa, xb, _ = _scene(5, 1500, 8.0, 3, 3)
    xa, xb = xa.astype(np.float32), xb.astype(np.float32)
    ia = jb = np.arange(3)
    exact = epipolar.epipolar_sums(xa, xb, F, ia, jb, 8.0, backend="numba", precision="float64")
    monkeypatch.setattr(epipolar, "rsqrt_within_bound", lambda: False)
    got = epipolar.epipolar_sums(xa, xb, F, ia, jb, 8.0, backend="numba", precision="mixed")
    np.testing.assert_array_equal(got[0], exact[0])
    np.testing.assert_array_equal(got[1], exact[1])


@pytest.mark.parametrize("above", [False, True])
def test_a_pair_the_estimate_cannot_settle_is_settled_by_the_refined_float32_sums(above,
                                                                                   monkeypatch):
    """tau within 1e-3 of a pair's mean: inside the error bound of the sums with the estimated
    1/sqrt (2^-10 and the rounding terms), outside that of the refined 1/sqrt (2^-20; its
    rounding terms reach ~1e-4 on points spread over the image). The second try in float32
    decides it as float64 does, with a float32 sum (not float64's bits); without that try the
    pair is summed in float64."""
    if not epipolar.have_numba():
        return
    assert epipolar.refined_rsqrt_within_bound()  # on this machine the second try runs
    F, xa, xb, _ = _scene(7, 4000, 8.0, 1, 1)
    xa, xb = xa.astype(np.float32), xb.astype(np.float32)
    one = np.zeros(1, np.int64)
    exact = epipolar.epipolar_sums(xa, xb, F, one, one, 1e3, early_exit=False, backend="numba",
                                   precision="float64")
    mean = exact[0][0] / exact[1][0]
    tau = mean * (1 + 1e-3) if above else mean * (1 - 1e-3)
    got = epipolar.epipolar_sums(xa, xb, F, one, one, tau, backend="numba", precision="mixed")
    assert (got[0][0] < tau * got[1][0]) == above
    assert got[0][0] != exact[0][0] and got[0][0] == pytest.approx(exact[0][0], rel=1e-6)
    monkeypatch.setattr(epipolar, "refined_rsqrt_within_bound", lambda: False)
    got = epipolar.epipolar_sums(xa, xb, F, one, one, tau, backend="numba", precision="mixed")
    assert (got[0][0] < tau * got[1][0]) == above
    assert got[0][0] == exact[0][0]


def _ring_scene(seed: int, n: int, tau: float, per_cam: int, cams: int = 3):
    """cams cameras seeing per_cam people each (person p in every camera), every vertex of a
    camera's detection moved off the true spot by noise around tau / 2 px."""
    rig = ring_rig(cams)
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (per_cam, n, 3)) * [0.3, 0.2, 0.9] + [0, 0, 1]
    X[:, :, :2] += rng.uniform(-3, 3, (per_cam, 1, 2))
    points = {}
    for c, cam in enumerate(rig):
        x = cam.project_rectified(X)
        points[c] = x + rng.normal(0, 1, x.shape) * rng.uniform(0.2, 1.5, (per_cam, 1, 1)) * tau / 2
    F = {(a, b): fundamental_matrix(rig.cameras[a], rig.cameras[b])
         for a in range(cams) for b in range(a + 1, cams)}
    return rig, points, F, rng


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 2600), symmetric=st.booleans(),
       tau=st.floats(1.0, 12.0), missing=st.sampled_from([0.0, 0.01, 0.3]),
       at_epipole=st.booleans(), early=st.booleans())
# detections of several blocks: the float32 loops sum in chunks while prefetching the next
# pair's blocks (one pair alone and two sharing an a-side detection)
@example(seed=3, n=4400, symmetric=True, tau=8.0, missing=0.01, at_epipole=False, early=True)
@example(seed=4, n=4400, symmetric=False, tau=8.0, missing=0.0, at_epipole=True, early=False)
def test_frame_sums_of_all_camera_pairs_decide_like_the_reference(seed, n, symmetric, tau, missing,
                                                                  at_epipole, early):
    """One call for the pairs of three camera pairs (each detection in several pairs, so runs of
    pairs share their a-side lines) decides like the numpy reference per camera pair, sums
    accepted pairs in full, with missing points and a detection at an epipole."""
    rig, points, F, rng = _ring_scene(seed, n, tau, 4)
    for c in points:
        points[c][rng.random(points[c].shape[:2]) < missing] = np.nan
    if at_epipole:  # camera 0's detection 1: some points at camera 0's epipole of pair (0, 1)
        e_a = np.linalg.svd(F[(0, 1)])[2][-1]
        points[0][1, ::3] = e_a[:2] / e_a[2]
    points = {c: x.astype(np.float32) for c, x in points.items()}
    pairs = [(a, b) for a, b in F for _ in range(6)]
    ca = np.array([a for a, _ in pairs])
    cb = np.array([b for _, b in pairs])
    da = rng.integers(0, 4, ca.size)
    db = np.where(rng.random(ca.size) < 0.5, da, rng.integers(0, 4, ca.size))
    want_reject = np.zeros(ca.size, bool)
    want_mean = np.zeros(ca.size)
    want_used = np.zeros(ca.size, np.int64)
    for (a, b) in F:
        s = np.flatnonzero((ca == a) & (cb == b))
        mean, common = _full_mean(points[a].astype(np.float64), points[b].astype(np.float64),
                             F[(a, b)], da[s], db[s], symmetric)
        want_reject[s] = ~(mean < tau)
        want_mean[s] = mean
        want_used[s] = common
    near_tie = np.abs(want_mean - tau) < 1e-9 * tau
    for backend, precision, rtol, atol in VARIANTS:
        sums, used = epipolar.frame_sums(points, F, ca, da, cb, db, tau, symmetric, early,
                                         backend, precision)
        reject = ~(sums < tau * used)
        assert np.array_equal(reject[~near_tie], want_reject[~near_tie]), (backend, precision)
        ok = ~reject
        np.testing.assert_allclose(sums[ok] / used[ok], want_mean[ok], rtol=rtol, atol=atol)
        # count_rest: every pair's count is complete, early exit or not; the sums unchanged
        counted = epipolar.frame_sums(points, F, ca, da, cb, db, tau, symmetric, early,
                                      backend, precision, count_rest=True)
        np.testing.assert_array_equal(counted[0], sums)
        np.testing.assert_array_equal(counted[1], want_used)
        # the per-camera-pair entry point gives the same numbers
        for (a, b) in F:
            s = np.flatnonzero((ca == a) & (cb == b))
            one = epipolar.epipolar_sums(points[a], points[b], F[(a, b)], da[s], db[s], tau,
                                         symmetric, early, backend, precision)
            assert np.array_equal(~(one[0] < tau * one[1]), reject[s])
            np.testing.assert_allclose(one[0][ok[s]], sums[s][ok[s]], rtol=1e-12)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(400, 3000), stride=st.integers(2, 5),
       symmetric=st.booleans(), early=st.booleans())
def test_a_screen_read_in_place_sums_like_its_contiguous_copy(seed, n, stride, symmetric, early):
    """The screening subset is read where it lies (runs of SCREEN_RUN points in each
    detection's row): every backend gives the numbers it gives on a contiguous copy of the
    same points."""
    _, points, F, rng = _ring_scene(seed, n, 8.0, 4)
    points = {c: x.astype(np.float32) for c, x in points.items()}
    screen = {c: screening.screen_rows(x, stride) for c, x in points.items()}
    copied = {c: rows.contiguous() for c, rows in screen.items()}
    assert all(rows.run and np.shares_memory(rows.flat, points[c]) for c, rows in screen.items())
    pairs = [(a, b) for a, b in F for _ in range(5)]
    ca, cb = np.array([a for a, _ in pairs]), np.array([b for _, b in pairs])
    da, db = rng.integers(0, 4, ca.size), rng.integers(0, 4, ca.size)
    for backend, precision, _, _ in VARIANTS:
        got = epipolar.frame_sums(screen, F, ca, da, cb, db, 8.0, symmetric, early, backend,
                                  precision)
        want = epipolar.frame_sums(copied, F, ca, da, cb, db, 8.0, symmetric, early, backend,
                                   precision)
        np.testing.assert_array_equal(got[0], want[0], err_msg=f"{backend} {precision}")
        np.testing.assert_array_equal(got[1], want[1], err_msg=f"{backend} {precision}")


def test_frame_sums_rejects_bad_input_with_the_input_named():
    x = np.zeros((2, 10, 2), np.float32)
    F = {(0, 1): np.eye(3)[[1, 0, 2]]}
    zero, one = np.array([0]), np.array([1])
    with pytest.raises(ValueError, match=r"no points for camera\(s\) \[2\]"):
        epipolar.frame_sums({0: x, 1: x}, F, zero, zero, np.array([2]), zero, 8.0)
    with pytest.raises(ValueError, match=r"no fundamental matrix for camera pair \(1, 0\)"):
        epipolar.frame_sums({0: x, 1: x}, F, one, zero, zero, zero, 8.0)
    with pytest.raises(ValueError, match="one n for every camera"):
        epipolar.frame_sums({0: x, 1: x[:, :5]}, F, zero, zero, one, zero, 8.0)
    with pytest.raises(ValueError, match="detection index out of range"):
        epipolar.frame_sums({0: x, 1: x}, F, zero, zero, one, np.array([2]), 8.0)
    with pytest.raises(ValueError, match="equal-length 1D"):
        epipolar.frame_sums({0: x, 1: x}, F, zero, zero, one, np.array([0, 1]), 8.0)


@pytest.mark.parametrize("intrinsic, attribute", [("wide_vectors", "_WIDE"),
                                                   ("estimated_rsqrt", "_ESTIMATE")])
def test_the_kernels_function_attributes_reach_llvm(intrinsic, attribute):
    """The kernels' LLVM function attributes are still written with the installed
    numba/llvmlite: 512-bit vectors (else narrower, silently) and, on x86-64, the float32
    1/sqrt as the estimate alone (else refined, silently: slower, still correct)."""
    numba = pytest.importorskip("numba")
    import platform

    from maem_ros.core.association.gates import epipolar_jit
    if intrinsic == "estimated_rsqrt" and platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("the estimate alone is used on x86-64 only")
    mark = getattr(epipolar_jit, intrinsic)

    @numba.njit
    def plus_one(x):
        mark()
        return x + 1

    assert plus_one(1) == 2
    assert getattr(epipolar_jit, attribute) in plus_one.inspect_llvm(plus_one.signatures[0])


def _runs(pa: np.ndarray, fk: np.ndarray) -> list[tuple[int, ...]]:
    """The runs of a pair order: consecutive pairs of one a-side detection and camera pair."""
    cut = np.flatnonzero((np.diff(pa) != 0) | (np.diff(fk) != 0)) + 1
    return [tuple(r) for r in np.split(np.arange(pa.size), cut)]


def _lru_misses(order: np.ndarray, pa: np.ndarray, pb: np.ndarray, cap: int) -> int:
    """Detections read from outside an LRU cache of cap detections, pairs in ``order``."""
    recent: list[int] = []
    misses = 0
    for s in order:
        for d in (int(pa[s]), int(pb[s])):
            if d in recent:
                recent.remove(d)
            else:
                misses += 1
                recent = recent[-(cap - 1):]
            recent.append(d)
    return misses


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.integers(1, 60), st.integers(2, 12))
def test_locality_order_keeps_runs_whole_and_in_order(seed, detections, cap):
    if not epipolar.have_numba():
        pytest.skip("numba not installed")
    from maem_ros.core.association.gates import epipolar_kernel
    rng = np.random.default_rng(seed)
    S = int(rng.integers(1, 4 * detections + 1))
    key = np.unique(rng.integers(0, 3 * detections * detections, S))  # (a, camera pair, b)
    pa, fk, pb = key // (3 * detections), key // detections % 3, key % detections
    perm = epipolar_kernel.locality_order(pa, pb, fk, detections, cap)
    assert sorted(perm.tolist()) == list(range(key.size))
    runs = _runs(pa, fk)
    got = _runs(pa[perm], fk[perm])
    assert sorted(tuple(perm[list(r)]) for r in got) == sorted(runs)  # whole, in order


def _ring_pairs(D: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(pa, pb) of the pairs along a ring of D detections numbered at random (each with its
    two neighbours), in the kernel's input order (by a side)."""
    label = np.random.default_rng(seed).permutation(D)
    a, b = label, np.roll(label, -1)
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], 1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order, 0], pairs[order, 1]


def test_locality_order_reads_a_ring_of_detections_from_cache():
    """Pairs along a ring of 200 detections, given by a side (one detection's neighbours far
    apart in that order): taken in locality_order, nearly every detection comes from outside
    an LRU cache of 8 detections once, not once per pair."""
    if not epipolar.have_numba():
        pytest.skip("numba not installed")
    from maem_ros.core.association.gates import epipolar_kernel
    D = 200
    pa, pb = _ring_pairs(D, 3)
    perm = epipolar_kernel.locality_order(pa, pb, np.zeros(D, np.int64), D, 8)
    assert _lru_misses(np.arange(D), pa, pb, 8) > 1.5 * D
    assert _lru_misses(perm, pa, pb, 8) <= D + 10


@pytest.mark.parametrize("symmetric", [True, False])
def test_several_blocks_sum_each_pair_as_in_the_given_order(symmetric):
    """With several blocks the kernel takes the runs in locality_order: every pair's sums
    and counts are those of the given order, bit for bit (ordered_sums), whether the pairs
    are summed whole or exit early, with runs of one and two pairs and a block with a missing
    point."""
    if not epipolar.have_numba():
        pytest.skip("numba not installed")
    from maem_ros.core.association.gates import epipolar_kernel
    rng = np.random.default_rng(7)
    D, n = 40, 3 * epipolar.BLOCK + 100
    F = fundamental_matrix(*two_facing_cameras())
    x = rng.uniform(200, 1800, (D, n, 2)).astype(np.float32)
    x[2, 5] = np.nan
    x.setflags(write=False)
    det_addr = x.ctypes.data + np.arange(D, dtype=np.int64) * x.strides[0]
    pa, pb = _ring_pairs(D, 5)
    pa, pb = np.concatenate([pa, pa[:5]]), np.concatenate([pb, (pb[:5] + 7) % D])
    keep = np.lexsort((pb, pa))  # runs of one and two pairs
    pa, pb = pa[keep], pb[keep]
    fk = np.zeros(pa.size, np.int64)
    assert not np.array_equal(epipolar_kernel.locality_order(
        pa, pb, fk, D, epipolar_kernel.LOCALITY_BLOCKS), np.arange(pa.size))
    unit = epipolar.pair_matrices({(0, 1): F}).unit
    blocks = epipolar.block_order(n)

    def sums(kernel, tau):
        return kernel(x.reshape(-1), det_addr, np.full((D, blocks.shape[0], 2), np.nan), unit,
                      fk, pa, pb, blocks, n, tau, True, symmetric, True, True, True)

    means = np.divide(*sums(epipolar_kernel.ordered_sums, np.inf)[:2])
    # every pair passes and is summed whole; every pair exits early
    for tau, early in ((np.inf, False), (float(means.min()) / 5, True)):
        got, given = sums(epipolar_kernel.sums_kernel, tau), sums(epipolar_kernel.ordered_sums,
                                                                  tau)
        assert np.all(given[2] < given[1]) == early
        for g, w in zip(got, given):
            np.testing.assert_array_equal(g, w)
