"""MAEM stage 3 (core/triangulation/ransac.py) against exact geometric answers."""
from __future__ import annotations

import numpy as np
import pytest
from helpers_scene import cluster, people, project_frames, ring_rig
from hypothesis import given, settings, strategies as st

from maem_ros.core.geometry.multiview import dlt
from maem_ros.core.triangulation.ransac import Poses, TriangulationParams, triangulate


# ---------------------------------------------------------------------------------------- dlt
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), views=st.integers(2, 6))
def test_dlt_recovers_noiseless_points(seed: int, views: int) -> None:
    rng = np.random.default_rng(seed)
    rig = ring_rig(views, phase=rng.uniform(0, 2 * np.pi))
    X = rng.uniform([-5, -4, 0], [5, 4, 2.5], (7, 3))
    P = np.stack([c.P for c in rig])  # (M,3,4)
    uv = np.stack([c.project_rectified(X) for c in rig], axis=1)  # (7,M,2)
    out = dlt(P, uv)  # P broadcasts over the batch of points
    assert out.shape == (7, 3)
    np.testing.assert_allclose(out, X, atol=1e-6)


def test_dlt_broadcasts_batch_dims() -> None:
    rig = ring_rig(3)
    X = people(2, 5).reshape(2, 5, 3)
    P = np.stack([c.P for c in rig])
    uv = np.stack([c.project_rectified(X) for c in rig], axis=-2)  # (2,5,3,2)
    out = dlt(P[None, None], uv, np.ones((2, 5, 3)))
    np.testing.assert_allclose(out, X, atol=1e-6)


def test_dlt_nan_with_fewer_than_two_usable_views() -> None:
    rig = ring_rig(3)
    X = np.array([0.5, 0.2, 1.0])
    P = np.stack([c.P for c in rig])
    uv = np.stack([c.project_rectified(X) for c in rig])
    one_finite = uv.copy()
    one_finite[1:] = np.nan
    assert np.isnan(dlt(P, one_finite)).all()
    assert np.isnan(dlt(P, uv, np.array([1.0, 0.0, 0.0]))).all()
    # two views left after dropping a NaN one still triangulate exactly
    two = uv.copy()
    two[0] = [np.nan, 3.0]
    np.testing.assert_allclose(dlt(P, two), X, atol=1e-6)


def test_dlt_same_ray_twice_is_nan() -> None:
    cam = ring_rig(1)[0]
    X = np.array([0.3, 0.1, 1.2])
    uv = cam.project_rectified(X)
    assert np.isnan(dlt(np.stack([cam.P, cam.P]), np.stack([uv, uv]))).all()


def test_dlt_weights() -> None:
    rig = ring_rig(3)
    X = np.array([1.0, -0.5, 1.1])
    P = np.stack([c.P for c in rig])
    uv = np.stack([c.project_rectified(X) for c in rig])
    uv_bad = uv.copy()
    uv_bad[2] += [40.0, -25.0]  # one view disagrees
    equal = dlt(P, uv_bad, np.ones(3))
    down = dlt(P, uv_bad, np.array([1.0, 1.0, 0.05]))
    assert np.linalg.norm(down - X) < 0.2 * np.linalg.norm(equal - X)
    # a common scale of all weights changes nothing; weight 0 == view absent
    np.testing.assert_allclose(dlt(P, uv_bad, np.full(3, 7.0)), equal, atol=1e-9)
    np.testing.assert_allclose(dlt(P, uv_bad, np.array([1.0, 1.0, 0.0])), X, atol=1e-6)
    np.testing.assert_allclose(dlt(P, uv_bad, None), equal, atol=1e-12)


def test_dlt_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="P"):
        dlt(np.zeros((2, 3, 3)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="uv"):
        dlt(np.zeros((2, 3, 4)), np.zeros((2, 3)))


# -------------------------------------------------------------------------------- triangulate
def test_noiseless_clusters_exact() -> None:
    rig = ring_rig(6)
    X = people(4, 70)
    frames = project_frames(rig, X)
    clusters = [cluster(*[(c, p) for c in range(6)]) for p in range(4)]
    out = triangulate(rig, frames, clusters, TriangulationParams())
    assert isinstance(out, Poses) and out.joints.shape == (4, 70, 3)
    np.testing.assert_allclose(out.joints, X, atol=1e-6)
    assert (out.views == 6).all() and (out.inliers == 6).all()
    # the default score: the paper's (mean detection score) times the confidence, which is 1 for
    # exact views up to the prior noise
    assert np.all((out.scores > 0.5 * 0.95) & (out.scores < 0.95))
    paper = triangulate(rig, frames, clusters, TriangulationParams(pose_score="paper"))
    np.testing.assert_allclose(paper.scores, 0.95)


def test_cluster_order_and_subsets_of_views() -> None:
    rig = ring_rig(5)
    X = people(3, 13, seed=3)
    frames = project_frames(rig, X)
    # clusters of different sizes and member order, detection index != cluster index
    clusters = [cluster((4, 2), (0, 2)), cluster((1, 0), (3, 0), (2, 0)),
                cluster((2, 1), (0, 1), (3, 1), (4, 1))]
    out = triangulate(rig, frames, clusters)
    np.testing.assert_allclose(out.joints, X[[2, 0, 1]], atol=1e-6)
    assert out.views.tolist() == [2, 3, 4]
    assert out.inliers.tolist() == [[2] * 13, [3] * 13, [4] * 13]


def test_ransac_rejects_outlier_view() -> None:
    rig = ring_rig(5)
    X = people(1, 70, seed=5)
    frames = project_frames(rig, X)
    kp = frames["cam3"].kpts2d
    kp[0, :, :] += [60.0, -45.0]  # view 3 is wrong on every joint by 75 px
    out = triangulate(rig, frames, [cluster(*[(c, 0) for c in range(5)])], TriangulationParams(tau_kps=20.0))
    np.testing.assert_allclose(out.joints[0], X[0], atol=1e-6)
    assert (out.inliers == 4).all()
    # with a threshold above the outlier's offset nothing is rejected and the fit is pulled off
    loose = triangulate(rig, frames, [cluster(*[(c, 0) for c in range(5)])], TriangulationParams(tau_kps=1e4))
    assert (loose.inliers == 5).all()
    assert np.linalg.norm(loose.joints[0] - X[0], axis=-1).mean() > 1e-3


def test_nan_where_fewer_than_two_views() -> None:
    rig = ring_rig(3)
    X = people(1, 6, seed=7)
    frames = project_frames(rig, X)
    frames["cam0"].kpts2d[0, 0] = np.nan  # joint 0: only cam1, cam2 left -> still fine
    frames["cam1"].kpts2d[0, 1] = np.nan  # joint 1: cam0, cam2
    frames["cam2"].kpts2d[0, 1] = np.nan  # joint 1: now only cam0 -> NaN
    frames["cam0"].kpts2d[0, 2] = [np.inf, 5.0]
    frames["cam1"].kpts2d[0, 2] = np.nan  # joint 2: only cam2 -> NaN
    out = triangulate(rig, frames, [cluster((0, 0), (1, 0), (2, 0))])
    assert np.isnan(out.joints[0, 1]).all() and np.isnan(out.joints[0, 2]).all()
    assert out.inliers[0, 1] == 0 and out.inliers[0, 2] == 0
    np.testing.assert_allclose(out.joints[0, [0, 3, 4, 5]], X[0, [0, 3, 4, 5]], atol=1e-6)
    assert out.inliers[0, 0] == 2
    single = triangulate(rig, frames, [cluster((1, 0))])
    assert np.isnan(single.joints).all() and (single.inliers == 0).all() and single.views[0] == 1


def test_no_agreeing_pair_is_nan() -> None:
    rig = ring_rig(3)
    X = people(1, 4, seed=8)
    frames = project_frames(rig, X)
    frames["cam1"].kpts2d[0, 0] += 200.0
    frames["cam2"].kpts2d[0, 0] -= 300.0
    out = triangulate(rig, frames, [cluster((0, 0), (1, 0), (2, 0))], TriangulationParams(tau_kps=5.0))
    # three mutually inconsistent views: no hypothesis has two inliers -> NaN
    assert np.isnan(out.joints[0, 0]).all() and out.inliers[0, 0] == 0
    np.testing.assert_allclose(out.joints[0, 1:], X[0, 1:], atol=1e-6)


def test_tie_on_inliers_prefers_lower_error() -> None:
    rig = ring_rig(4)
    truth = np.array([[[0.2, 0.1, 1.0]]])
    other = truth + [0.0, 0.0, 0.8]  # a second candidate point, far in every view
    frames = project_frames(rig, truth)
    for k, name in enumerate(["cam0", "cam1"]):  # views 0,1 agree on `other`, slightly noisy
        frames[name].kpts2d[0, 0] = rig[name].project_rectified(other[0, 0]) + [1.5 * (-1) ** k, 1.0]
    # views 2,3 agree exactly on `truth`: both hypotheses have 2 inliers, truth has 0 error
    out = triangulate(rig, frames, [cluster((0, 0), (1, 0), (2, 0), (3, 0))],
                      TriangulationParams(tau_kps=10.0))
    assert out.inliers[0, 0] == 2
    np.testing.assert_allclose(out.joints[0, 0], truth[0, 0], atol=1e-6)


def test_score_weighted_refit_matches_weighted_dlt() -> None:
    rig = ring_rig(4)
    X = people(1, 10, seed=11)
    frames = project_frames(rig, X, noise_px=3.0, rng=np.random.default_rng(2))
    for k, cam in enumerate(rig):
        frames[cam.name].scores[:] = [0.3, 0.9, 0.6, 1.0][k]
    out = triangulate(rig, frames, [cluster(*[(c, 0) for c in range(4)])],
                      TriangulationParams(tau_kps=50.0, pose_score="paper"))
    assert (out.inliers == 4).all()
    P = np.stack([c.P for c in rig])
    uv = np.stack([frames[c.name].kpts2d[0] for c in rig], axis=1)  # (J,4,2)
    expected = dlt(P, uv, np.array([0.3, 0.9, 0.6, 1.0]))
    np.testing.assert_allclose(out.joints[0], expected, atol=1e-9)
    unweighted = dlt(P, uv)
    assert not np.allclose(expected, unweighted, atol=1e-6)
    np.testing.assert_allclose(out.scores, [0.7])


def test_empty_inputs() -> None:
    rig = ring_rig(3)
    frames = project_frames(rig, people(2, 13))
    out = triangulate(rig, frames, [])
    assert out.joints.shape == (0, 13, 3) and out.views.shape == (0,) and len(out) == 0


def test_bad_cluster_members() -> None:
    rig = ring_rig(3)
    frames = project_frames(rig, people(2, 5))
    with pytest.raises(ValueError, match="detection 5 out of range"):
        triangulate(rig, frames, [cluster((0, 0), (1, 5))])
    with pytest.raises(ValueError, match="camera index"):
        triangulate(rig, frames, [cluster((0, 0), (7, 0))])
    del frames["cam2"]
    with pytest.raises(ValueError, match="'cam2' has no detections"):
        triangulate(rig, frames, [cluster((0, 0), (2, 0))])


def test_params_validation() -> None:
    p = TriangulationParams.from_mapping({"tau_kps": 12, "frame_id": "world", "min_views": 3})
    assert p.tau_kps == 12.0 and p.min_views == 3
    with pytest.raises(ValueError, match="tau_kps"):
        TriangulationParams(tau_kps=-1)
    with pytest.raises(ValueError, match="min_views"):
        TriangulationParams(min_views=1)
    with pytest.raises(ValueError, match="tau_kps"):
        TriangulationParams.from_mapping({"tau_kps": "20"})


def test_min_views_parameter() -> None:
    rig = ring_rig(4)
    X = people(1, 5)
    frames = project_frames(rig, X)
    frames["cam3"].kpts2d[0, 0] = np.nan
    out = triangulate(rig, frames, [cluster(*[(c, 0) for c in range(4)])], TriangulationParams(min_views=4))
    assert np.isnan(out.joints[0, 0]).all()
    np.testing.assert_allclose(out.joints[0, 1:], X[0, 1:], atol=1e-6)


def test_real_cluster_type_if_available() -> None:
    from maem_ros.core.association import pipeline as association
    rig = ring_rig(3)
    X = people(1, 5)
    frames = project_frames(rig, X)
    cl = association.Cluster(members=np.array([[0, 0], [1, 0], [2, 0]]), costs=np.zeros(3))
    np.testing.assert_allclose(triangulate(rig, frames, [cl]).joints[0], X[0], atol=1e-6)


def test_ten_people_six_views_all_joints_from_every_view() -> None:
    """maem-bench's per-frame triangulation load (10 people x 70 joints, 6 views, 2 px noise):
    every joint triangulated from all 6 views, within a few cm of the truth, and a second call on
    the same input gives the same poses (no state carried between frames). Its speed is
    measured by maem-bench, not here."""
    rig = ring_rig(6)
    X = people(10, 70)
    frames = project_frames(rig, X, noise_px=2.0, rng=np.random.default_rng(0))
    clusters = [cluster(*[(c, p) for c in range(6)]) for p in range(10)]
    out = triangulate(rig, frames, clusters)
    assert out.joints.shape == (10, 70, 3)
    assert (out.views == 6).all()
    err = np.linalg.norm(out.joints - X, axis=-1)  # m
    assert err.max() < 0.1 and err.mean() < 0.03
    again = triangulate(rig, frames, clusters)
    np.testing.assert_array_equal(again.joints, out.joints)


def test_simulated_scene_exact_without_noise() -> None:
    """Noise-free simulated court: GT-built clusters triangulate to the GT joints."""
    import maem_ros.sim.scene as scene_mod
    from maem_ros.core.metrics.poses import evaluate_sequence

    scene = scene_mod.Scene(scene_mod.SceneConfig(frames=2, difficulty="none", num_vertices=50,
                                                  bystanders=0, players=4))
    gt = scene.gt_keypoints(1)  # (P,70,3)
    frames = {cam.name: scene.detections(cam.name, 1) for cam in scene.rig}
    members = [[] for _ in range(gt.shape[0])]
    for c, cam in enumerate(scene.rig):
        proj = cam.project_rectified(gt)  # (P,J,2)
        d = np.nanmean(np.linalg.norm(frames[cam.name].kpts2d[:, None] - proj[None], axis=-1), axis=-1)
        for det, person in enumerate(np.argmin(d, axis=1)):
            if d[det, person] < 1e-3:
                members[person].append((c, det))
    clusters = [cluster(*m) for m in members]
    out = triangulate(scene.rig, frames, clusters)
    assert all(len(m) >= 2 for m in members)
    np.testing.assert_allclose(out.joints, gt, atol=1e-6)
    res = evaluate_sequence([out.joints], [out.scores], [gt], [np.ones(gt.shape[:2], bool)])
    assert res["recall"] == 1.0 and res["ap75"] == 1.0 and res["mpjpe_mean"] < 1e-3


def test_tau_member_leaves_out_a_wrong_detection_as_a_whole() -> None:
    """Four views of person 0; cam2's detection is mostly person 1 (a body mixed from two
    overlapping people: 8 of 12 joints theirs). Per-keypoint RANSAC alone keeps the right
    joints but the cluster still lists cam2; tau_member drops it and re-triangulates."""
    rig = ring_rig(4)
    X = people(2, 12, seed=3)
    frames = project_frames(rig, X, noise_px=0.5, rng=np.random.default_rng(1))
    frames["cam2"].kpts2d[0, :8] = frames["cam2"].kpts2d[1, :8]
    cl = [cluster((0, 0), (1, 0), (2, 0), (3, 0))]
    paper = triangulate(rig, frames, cl, TriangulationParams())
    assert paper.rejected is None and paper.views[0] == 4
    out = triangulate(rig, frames, cl, TriangulationParams(tau_member=15.0))
    np.testing.assert_array_equal(out.rejected, [[False, False, True, False]])
    assert out.views[0] == 3 and (out.inliers[0] == 3).all()
    np.testing.assert_allclose(out.joints[0], X[0], atol=0.02)
    # a good cluster loses nothing; two views are never split (no third view to vote)
    clean = project_frames(rig, X, noise_px=0.5, rng=np.random.default_rng(1))
    good = triangulate(rig, clean, cl, TriangulationParams(tau_member=15.0))
    assert not good.rejected.any() and good.views[0] == 4
    two = triangulate(rig, frames, [cluster((1, 0), (2, 0))], TriangulationParams(tau_member=15.0))
    assert not two.rejected.any() and two.views[0] == 2
    with pytest.raises(ValueError, match="tau_member"):
        TriangulationParams(tau_member=-1.0)
