"""The fused RANSAC kernel (core.triangulation.ransac_kernel) against the numpy path and against a
straightforward per-cluster, per-keypoint loop (SVD least squares), on random geometry with
outlier views, missing (NaN) keypoints, absent members and zero scores."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from maem_ros.core.triangulation import ransac_kernel as triangulation_kernel
from maem_ros.core.triangulation.ransac import (TriangulationParams, _MIN_WEIGHT, _ransac_numpy,
                                         triangulate_members)
from maem_ros.core.triangulation.ransac_kernel import ransac_keypoints

needs_numba = pytest.mark.skipif(not triangulation_kernel.have_numba(),
                                 reason="numba not installed")


def ring_projections(k: int, rng: np.random.Generator) -> np.ndarray:
    """(k,3,4) rectified world->px projections of cameras on a ring looking at the court centre."""
    P = []
    for a in np.sort(rng.uniform(0, 2 * np.pi, k)):
        centre = np.array([10 * np.cos(a), 8 * np.sin(a), rng.uniform(2, 6)])
        z = np.array([0.0, 0.0, 1.0]) - centre
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        K = np.array([[rng.uniform(800, 1400), 0, 960], [0, 0, 540], [0, 0, 1]])
        K[1, 1] = K[0, 0]
        P.append(K @ np.hstack([R, (-R @ centre)[:, None]]))
    return np.stack(P)


def random_members(seed: int, clusters: int, views: int, joints: int):
    """Dense member arrays (triangulate_members' input) of a random scene: P_rig, cam (C,M),
    uv (C,M,J,2) with noise, outlier views, NaN keypoints, score (C,M) with zeros, present."""
    rng = np.random.default_rng(seed)
    P_rig = ring_projections(views + 2, rng)
    cam = np.stack([rng.permutation(views + 2)[:views] for _ in range(clusters)])
    X = (rng.uniform([-3, -3, 0], [3, 3, 2], (clusters, 1, 3))
         + rng.normal(0, 0.3, (clusters, joints, 3)))
    Xh = np.concatenate([X, np.ones(X.shape[:-1] + (1,))], -1)
    proj = np.einsum("cmik,cjk->cmji", P_rig[cam], Xh)
    uv = proj[..., :2] / proj[..., 2:] + rng.normal(0, 1.5, (clusters, views, joints, 2))
    outlier = rng.random((clusters, views, joints)) < 0.2
    uv += outlier[..., None] * rng.choice([-1, 1], uv.shape) * rng.uniform(40, 300, uv.shape)
    uv[rng.random(uv.shape) < 0.08] = np.nan  # one coordinate or both missing
    score = rng.uniform(0, 1, (clusters, views)) * (rng.random((clusters, views)) > 0.1)
    present = rng.random((clusters, views)) < 0.85
    return P_rig, cam, uv, score, present


def straightforward(P: np.ndarray, uv: np.ndarray, usable: np.ndarray, weight: np.ndarray,
                    tau: float, min_views: int) -> tuple[np.ndarray, np.ndarray]:
    """The method read literally: per cluster and keypoint, every pair of usable views gives a
    least-squares DLT (X4 = 1, numpy SVD); inliers: depth > 0 and error < tau; best: most
    inliers, then lowest mean inlier error, first on ties; refit weighted by the scores."""
    C, M, J = usable.shape

    def dlt(views, w):
        A = np.concatenate([np.stack([uv[c, m, j, 0] * P[c, m, 2] - P[c, m, 0],
                                      uv[c, m, j, 1] * P[c, m, 2] - P[c, m, 1]]) * wm
                            for m, wm in zip(views, w)])
        X, _, rank, _ = np.linalg.lstsq(A[:, :3], -A[:, 3], rcond=None)
        return X if rank == 3 else np.full(3, np.nan)

    X_out, n_out = np.full((C, J, 3), np.nan), np.zeros((C, J), np.int64)
    for c in range(C):
        for j in range(J):
            best_key, best_inl = -np.inf, []
            for a in range(M):
                for b in range(a + 1, M):
                    inl, errs = [], []
                    if usable[c, a, j] and usable[c, b, j]:
                        X = dlt([a, b], [1.0, 1.0])
                        for m in np.flatnonzero(usable[c, :, j]):
                            x, y, z = P[c, m] @ np.append(X, 1.0)
                            e = np.hypot(x / z - uv[c, m, j, 0], y / z - uv[c, m, j, 1])
                            if z > 0 and e < tau:
                                inl.append(m)
                                errs.append(e)
                        key = len(inl) - (np.mean(errs) if errs else 0.0) / (2 * tau)
                    else:
                        key = -1.0
                    if key > best_key:
                        best_key, best_inl = key, inl
            if len(best_inl) >= min_views:
                X_out[c, j] = dlt(best_inl, weight[c, best_inl])
                n_out[c, j] = len(best_inl) if np.isfinite(X_out[c, j]).all() else 0
    return X_out, n_out


def kernel_inputs(seed: int, clusters: int, views: int, joints: int):
    P_rig, cam, uv, score, present = random_members(seed, clusters, views, joints)
    usable = present[:, :, None] & np.isfinite(uv).all(-1)
    return P_rig[cam], uv, usable, np.maximum(score, _MIN_WEIGHT)


@needs_numba
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), clusters=st.integers(1, 4), views=st.integers(2, 7),
       joints=st.integers(1, 12), tau=st.floats(3.0, 40.0), min_views=st.integers(2, 4))
def test_kernel_equals_numpy_path(seed, clusters, views, joints, tau, min_views) -> None:
    P, uv, usable, weight = kernel_inputs(seed, clusters, views, joints)
    X, n = ransac_keypoints(P, uv, usable, weight, tau, min_views)
    X_ref, n_ref = _ransac_numpy(P, uv, usable, weight, tau, min_views)
    np.testing.assert_array_equal(n, n_ref)
    np.testing.assert_array_equal(np.isnan(X), np.isnan(X_ref))
    # the same float64 operations; only the order of the projection's dot products differs
    np.testing.assert_allclose(X, X_ref, rtol=1e-12, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), clusters=st.integers(1, 3), views=st.integers(2, 6),
       joints=st.integers(1, 8), tau=st.floats(5.0, 30.0), min_views=st.integers(2, 3))
def test_both_paths_equal_a_straightforward_loop(seed, clusters, views, joints, tau,
                                                 min_views) -> None:
    P, uv, usable, weight = kernel_inputs(seed, clusters, views, joints)
    X_ref, n_ref = straightforward(P, uv, usable, weight, tau, min_views)
    paths = [_ransac_numpy] + ([ransac_keypoints] if triangulation_kernel.have_numba() else [])
    for path in paths:
        X, n = path(P, uv, usable, weight, tau, min_views)
        np.testing.assert_array_equal(n, n_ref, err_msg=path.__name__)
        np.testing.assert_array_equal(np.isnan(X), np.isnan(X_ref), err_msg=path.__name__)
        np.testing.assert_allclose(X, X_ref, atol=1e-6, err_msg=path.__name__)


def test_random_scenes_exercise_every_case() -> None:
    """The generator above gives keypoints with outlier views left out, keypoints lost (NaN)
    and keypoints from every usable view, so the comparisons are not vacuous."""
    P, uv, usable, weight = kernel_inputs(11, 5, 6, 30)
    X, n = straightforward(P, uv, usable, weight, 20.0, 3)
    views = usable.sum(1)
    assert (np.isnan(X).all(-1) & (views >= 3)).any()  # lost although seen three times
    assert ((n > 0) & (n < views)).any()  # outliers rejected
    assert ((n > 2) & (n == views)).any()  # every view agrees
    assert (weight < 1e-2).any() and (~usable).any()


@needs_numba
@pytest.mark.parametrize("options", [{}, {"tau_member": 15.0}, {"left_right": True},
                                     {"min_views": 3, "tau_kps": 8.0}])
def test_backends_give_the_same_poses(options) -> None:
    """Through triangulate_members (left/right relabelling and member rejection included)."""
    J = 70  # the MHR70 convention, which left_right needs
    members = random_members(7, 6, 6, J)
    fast = TriangulationParams(ransac_backend="numba", **options)
    out = triangulate_members(*members, fast)
    ref = triangulate_members(*members, dataclasses.replace(fast, ransac_backend="numpy"))
    assert np.isfinite(out.joints).any() and np.isnan(out.joints).any()
    np.testing.assert_array_equal(np.isnan(out.joints), np.isnan(ref.joints))
    np.testing.assert_allclose(out.joints, ref.joints, rtol=1e-12, atol=1e-12)
    for name in ("views", "inliers", "detection_scores", "mirrored", "rejected"):
        np.testing.assert_array_equal(getattr(out, name), getattr(ref, name), err_msg=name)
    # the uncertainty score is a function of the joints: equal to the joints' rounding
    np.testing.assert_allclose(out.scores, ref.scores, rtol=1e-9)
    np.testing.assert_allclose(out.joint_std, ref.joint_std, rtol=1e-9)


def test_backend_parameter(monkeypatch) -> None:
    with pytest.raises(ValueError, match="ransac_backend"):
        TriangulationParams(ransac_backend="cuda")
    monkeypatch.setattr(triangulation_kernel, "have_numba", lambda: False)
    assert not triangulation_kernel.use_numba("auto")
    with pytest.raises(ValueError, match="ransac_backend: 'numba' requested but numba is not"):
        triangulation_kernel.use_numba("numba")
    members = random_members(3, 2, 4, 5)
    auto = triangulate_members(*members, TriangulationParams())  # falls back to numpy
    ref = triangulate_members(*members, TriangulationParams(ransac_backend="numpy"))
    np.testing.assert_array_equal(auto.joints, ref.joints)
