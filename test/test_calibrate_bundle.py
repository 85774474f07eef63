"""Unit tests of the shared bundle adjustment (core/calibrate/bundle.py) with geometric truth."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from maem_ros.core.calibrate.bundle import (BundleOptions, BundleProblem, bundle_adjust,
                                            robust_rho)
from helpers_calibrate import rotation_angle_deg
from helpers_scene import CALIBRATION_RING, ring_rig


def _observe(rig, X, rng, noise_px=0.0):
    """Observations of world points X (P,3) in every camera where they are in the image."""
    cams, pts, uvs = [], [], []
    for c, cam in enumerate(rig):
        uv = cam.project_rectified(X)
        ok = np.all(np.isfinite(uv), 1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.flatnonzero(ok)
        cams.append(np.full(idx.size, c))
        pts.append(idx)
        uvs.append(uv[idx] + rng.normal(0, noise_px, (idx.size, 2)))
    return np.concatenate(cams), np.concatenate(pts), np.concatenate(uvs)


def _perturbed(rig, rng, deg, metres):
    R = np.stack([Rotation.from_rotvec(rng.normal(size=3) * np.radians(deg) / np.sqrt(3)).as_matrix()
                  @ c.R for c in rig])
    t = np.stack([c.t + rng.normal(0, metres, 3) for c in rig])
    R[0], t[0] = rig[0].R, rig[0].t  # the gauge camera
    return R, t


def _points(rng, n):
    return np.column_stack([rng.uniform(-6, 6, n), rng.uniform(-4, 4, n), rng.uniform(0, 2, n)])


def test_free_points_recovered_from_a_rough_start():
    rng = np.random.default_rng(1)
    rig = ring_rig(4, height=4.0, jitter_seed=0, **CALIBRATION_RING)
    X = _points(rng, 400)
    cam, pt, uv = _observe(rig, X, rng)
    R0, t0 = _perturbed(rig, rng, 5.0, 0.3)
    scale = np.linalg.norm(rig[1].center - rig[0].center)
    prob = BundleProblem(K=np.stack([c.K for c in rig]), R=R0, t=t0,
                         points=X + rng.normal(0, 0.2, X.shape), obs_camera=cam, obs_point=pt,
                         obs_uv=uv)
    res = bundle_adjust(prob, BundleOptions(fixed_cameras=(0,)))
    # the free-point problem's scale is a gauge: compare after fixing it by camera 1's centre
    s = scale / np.linalg.norm(res.centers[1] - res.centers[0])
    for c, cam_true in enumerate(rig):
        assert rotation_angle_deg(res.R[c], cam_true.R) < 1e-4
        centre = res.centers[0] + s * (res.centers[c] - res.centers[0])
        assert np.linalg.norm(centre - cam_true.center) < 1e-4
    assert np.nanmax(res.errors()) < 1e-4
    assert res.inliers.all()


def test_outliers_rejected_and_rig_recovered():
    rng = np.random.default_rng(2)
    rig = ring_rig(5, height=4.0, jitter_seed=0, **CALIBRATION_RING)
    X = _points(rng, 500)
    cam, pt, uv = _observe(rig, X, rng, noise_px=0.5)
    bad = rng.random(cam.size) < 0.05
    uv = uv.copy()
    uv[bad] += rng.uniform(30, 200, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    R0, t0 = _perturbed(rig, rng, 3.0, 0.2)
    prob = BundleProblem(K=np.stack([c.K for c in rig]), R=R0, t=t0, points=X + rng.normal(0, 0.1, X.shape),
                         obs_camera=cam, obs_point=pt, obs_uv=uv)
    res = bundle_adjust(prob, BundleOptions(covariance=True))
    assert not res.inliers[bad].any()
    assert res.inliers[~bad].mean() > 0.97
    for c, cam_true in enumerate(rig):
        assert rotation_angle_deg(res.R[c], cam_true.R) < 0.05
    # covariance: fixed camera none, others small but positive
    assert np.all(res.camera_cov[0] == 0)
    sd_rot = np.degrees(np.sqrt(np.trace(res.camera_cov[1][:3, :3])))
    assert 0 < sd_rot < 0.05


def test_rigid_objects_fix_scale_and_refine_focal():
    """Board mode: a planar grid at several poses (rigid objects), one camera's focal off."""
    rng = np.random.default_rng(3)
    rig = ring_rig(3, radius=3.0, height=1.5, jitter_seed=0, aim_jitter=0.2, **CALIBRATION_RING)
    gx, gy = np.meshgrid(np.arange(9) * 0.1, np.arange(6) * 0.1)
    board = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    L = board.shape[0]
    poses = 12
    oR = Rotation.from_euler("xyz", rng.uniform(-0.6, 0.6, (poses, 3))).as_matrix() \
        @ Rotation.from_euler("x", np.pi / 2).as_matrix()
    ot = np.column_stack([rng.uniform(-0.5, 0.5, poses), rng.uniform(-0.5, 0.5, poses), rng.uniform(0.8, 1.5, poses)])
    X = (np.einsum("oij,lj->oli", oR, board) + ot[:, None]).reshape(-1, 3)
    cam, pt, uv = _observe(rig, X, rng, noise_px=0.2)
    K = np.stack([c.K for c in rig])
    K_start = K.copy()
    K_start[2, :2, :2] *= 1.03  # camera 2's focal 3 % off
    R0, t0 = _perturbed(rig, rng, 2.0, 0.1)
    prob = BundleProblem(K=K_start, R=R0, t=t0, points=np.zeros_like(X), obs_camera=cam, obs_point=pt,
                         obs_uv=uv, point_object=np.repeat(np.arange(poses), L),
                         model=np.tile(board, (poses, 1)),
                         object_R=Rotation.from_rotvec(rng.normal(0, 0.03, (poses, 3))).as_matrix() @ oR,
                         object_t=ot + rng.normal(0, 0.05, ot.shape))
    res = bundle_adjust(prob, BundleOptions(refine_focal=True))
    assert abs(res.focal_scale[2] * 1.03 - 1) < 2e-3
    for c, cam_true in enumerate(rig):
        assert rotation_angle_deg(res.R[c], cam_true.R) < 0.1
        assert np.linalg.norm(res.centers[c] - cam_true.center) < 0.01  # metric: the board's scale
    assert np.nanmedian(res.errors()) < 0.5


def test_groups_rejected_whole():
    rng = np.random.default_rng(4)
    rig = ring_rig(3, height=4.0, jitter_seed=0, **CALIBRATION_RING)
    X = _points(rng, 300)
    cam, pt, uv = _observe(rig, X, rng, noise_px=0.3)
    group = cam * 1000 + pt // 10  # "detections" of 10 points each
    wrong = group == group[cam == 1][0]
    uv = uv.copy()
    uv[wrong] += 25.0  # a whole detection shifted (a wrong association)
    prob = BundleProblem(K=np.stack([c.K for c in rig]), R=np.stack([c.R for c in rig]),
                         t=np.stack([c.t for c in rig]), points=X, obs_camera=cam, obs_point=pt,
                         obs_uv=uv, obs_group=group)
    res = bundle_adjust(prob)
    assert not res.inliers[wrong].any()
    assert res.inliers[~wrong].mean() > 0.95


def test_robust_losses_match_a_numerical_derivative():
    s = np.linspace(0.0, 5000.0, 11)
    for loss in ("linear", "cauchy", "soft_l1", "huber"):
        rho, drho = robust_rho(loss, s, 20.0)
        num = (robust_rho(loss, s + 1e-4, 20.0)[0] - robust_rho(loss, s - 1e-4, 20.0)[0]) / 2e-4
        np.testing.assert_allclose(drho[1:], num[1:], rtol=1e-4)
        assert abs(drho[0] - 1) < 1e-9
    with pytest.raises(ValueError, match="unknown robust loss"):
        robust_rho("tukey", s, 1.0)


def test_bad_problem_named():
    with pytest.raises(ValueError, match="obs_uv holds NaN"):
        BundleProblem(K=np.eye(3)[None], R=np.eye(3)[None], t=np.zeros((1, 3)), points=np.zeros((1, 3)),
                      obs_camera=[0], obs_point=[0], obs_uv=[[np.nan, 1.0]])


def test_intrinsic_jacobian_matches_finite_differences():
    """The camera block's analytic Jacobian (pose and every intrinsic refined, a lens with all
    five plumb_bob terms) against central differences of the residuals."""
    from maem_ros.core.calibrate.bundle_solver import INTRINSIC_NAMES, Observations, State, project
    rng = np.random.default_rng(11)
    rig = ring_rig(2, height=3.0, jitter_seed=1, **CALIBRATION_RING)
    X = _points(rng, 40)
    cam, pt, uv = _observe(rig, X, rng, noise_px=0.5)
    D = np.array([[-0.2, 0.06, 8e-4, -5e-4, 0.01], [-0.1, 0.02, -3e-4, 6e-4, -0.004]])
    prob = BundleProblem(K=np.stack([c.K for c in rig]), R=np.stack([c.R for c in rig]),
                         t=np.stack([c.t for c in rig]), points=X, obs_camera=cam, obs_point=pt,
                         obs_uv=uv, dist=D)
    args = (prob.R, prob.t, prob.focal_scale, prob.K, prob.dist, prob.points, prob.object_R,
            prob.object_t, False, False, INTRINSIC_NAMES)
    st = State(*args)
    ob = Observations(prob, np.ones(cam.size, bool))
    blk = ob.blocks[1]
    _, Jc, _, _ = project(st, ob, blk, True)
    for col in range(st.dc):
        h = np.zeros((2, st.dc))
        h[blk.cam, col] = 1e-6
        plus = project(st.updated(h, 0.0, np.zeros((0, 6))), ob, blk, False)
        minus = project(st.updated(-h, 0.0, np.zeros((0, 6))), ob, blk, False)
        numeric = (plus - minus) / 2e-6
        np.testing.assert_allclose(Jc[:, col].T, numeric, rtol=1e-4, atol=1e-4 * np.abs(numeric).max(),
                                   err_msg=(("rx ry rz tx ty tz".split()) + list(INTRINSIC_NAMES))[col])


def test_options_refuse_unknown_or_doubled_intrinsics():
    with pytest.raises(ValueError, match="unknown intrinsics"):
        BundleOptions(intrinsics=("fx", "skew"))
    with pytest.raises(ValueError, match="not with refine_focal"):
        BundleOptions(intrinsics=("fx",), refine_k1=True)
