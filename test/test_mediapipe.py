"""The mediapipe frontend backend and the BlazePose-33 convention.

Unit tests run a scripted stand-in for mp.solutions.pose.Pose (geometric ground truth); the
real-footage tests need the mediapipe wheel (make mediapipe) and the pose2sim wheel (fetched
into the cache) and skip with the reason otherwise.
"""
from __future__ import annotations

import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from maem_ros.core.association.pipeline import AssociationParams, associate
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.skeleton import (BLAZEPOSE_33, COCO_17, SPORTCENTER_13, convention_for,
                                    convert, get_convention)
from maem_ros.core.triangulation.ransac import TriangulationParams, triangulate
from maem_ros.frontend.base import make_estimator
from maem_ros.frontend.mediapipe_pose import INSTALL_HELP, import_mediapipe
from maem_ros.frontend.rectify import Rectifier
from maem_ros.params import load_node_params


# ---- convention ----------------------------------------------------------------------------
def test_blazepose_maps_to_sportcenter_13_and_coco_17():
    assert BLAZEPOSE_33.num_joints == 33 and convention_for(33) is BLAZEPOSE_33
    assert SPORTCENTER_13.indices_in(BLAZEPOSE_33) == (0, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26,
                                                       27, 28)
    assert COCO_17.indices_in(BLAZEPOSE_33) == (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24,
                                                25, 26, 27, 28)
    x = np.arange(2 * 33 * 3, dtype=float).reshape(2, 33, 3)
    sc = convert(x, SPORTCENTER_13, "blazepose_33")
    np.testing.assert_array_equal(sc[:, 5], x[:, 15])  # left wrist
    # the MHR70 path gives the same joints by name as the index table of doc/design.md §7
    mhr = np.arange(70 * 2, dtype=float).reshape(70, 2)
    np.testing.assert_array_equal(convert(mhr, SPORTCENTER_13, "mhr70"),
                                  SPORTCENTER_13.select(mhr))


def test_blazepose_bones_and_bad_conversions():
    assert len(BLAZEPOSE_33.bones) == 35  # mp.solutions.pose.POSE_CONNECTIONS
    assert all(0 <= a < 33 and 0 <= b < 33 for a, b in BLAZEPOSE_33.bones)
    with pytest.raises(ValueError, match="mhr70 has no left_eye_inner"):
        convert(np.zeros((70, 2)), BLAZEPOSE_33, "mhr70")
    with pytest.raises(ValueError, match="13 joints .convention 'blazepose_33', 33 joints"):
        convert(np.zeros((13, 2)), COCO_17, "blazepose_33")
    # the convention is inferred from the joint count
    np.testing.assert_array_equal(convert(np.arange(66.0).reshape(33, 2), SPORTCENTER_13)[1],
                                  [22.0, 23.0])
    with pytest.raises(ValueError, match="not a subset of mhr70"):
        BLAZEPOSE_33.select(np.zeros((70, 3)))


# ---- backend with a scripted model ---------------------------------------------------------
def _camera() -> Camera:
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    return Camera("cam0", K, np.eye(3), np.zeros(3), 640, 480)


def _body(seed: int) -> np.ndarray:
    """(33,3) a plausible hip-centred body (metres, y down), slightly random."""
    rng = np.random.default_rng(seed)
    base = np.zeros((33, 3))
    base[:11] = [0, -0.65, -0.05]  # face
    base[11:23:2, 0], base[12:23:2, 0] = 0.2, -0.2  # left / right arm chain
    base[11:13, 1], base[13:15, 1], base[15:23, 1] = -0.5, -0.2, 0.05
    base[23::2, 0], base[24::2, 0] = 0.1, -0.1
    base[23:25, 1], base[25:27, 1], base[27:33, 1] = 0.0, 0.45, 0.85
    return base + rng.normal(0, 0.03, size=(33, 3))


class ScriptedPose:
    """Stand-in for mp Pose: returns the listed people in order, one per call, and checks that
    each call sees the earlier people greyed out."""

    def __init__(self, people, camera: Camera):
        self.people, self.camera, self.calls = people, camera, []

    def process(self, rgb: np.ndarray):
        self.calls.append(rgb.copy())
        k = len(self.calls) - 1
        if k >= len(self.people):
            return SimpleNamespace(pose_landmarks=None, pose_world_landmarks=None,
                                   segmentation_mask=None)
        world, R, t, vis = self.people[k]
        Xc = world @ R.T + t
        uv = Xc[:, :2] / Xc[:, 2:] @ self.camera.K[:2, :2].T + self.camera.K[:2, 2]
        h, w = rgb.shape[:2]
        mask = np.zeros((h, w), np.float32)
        lo, hi = np.floor(uv.min(0)).astype(int), np.ceil(uv.max(0)).astype(int)
        mask[max(lo[1], 0):hi[1], max(lo[0], 0):hi[0]] = 1.0
        lm = SimpleNamespace(landmark=[SimpleNamespace(x=u / w, y=v / h, visibility=s)
                                       for (u, v), s in zip(uv, vis)])
        wl = SimpleNamespace(landmark=[SimpleNamespace(x=x, y=y, z=z) for x, y, z in world])
        return SimpleNamespace(pose_landmarks=lm, pose_world_landmarks=wl, segmentation_mask=mask)


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_two_people_masked_and_placed_in_the_camera():
    cam = _camera()
    people = [(_body(0), _rot(0.3), np.array([-0.8, 0.1, 4.0]), np.full(33, 0.9)),
              (_body(1), _rot(-0.5), np.array([0.9, 0.0, 5.0]), np.full(33, 0.7))]
    fake = ScriptedPose(people, cam)
    est = make_estimator("mediapipe", {"pose_factory": lambda o: fake, "mask_dilate": 3},
                         Rig([cam]))
    image = np.full((480, 640, 3), 200, np.uint8)
    dets = est.estimate(cam, 123, image)
    assert dets.n == 2 and dets.num_vertices == 0 and dets.num_joints == 33
    assert len(fake.calls) == 3  # two people, then a pass that finds nobody
    # the second pass saw the first person greyed out, the first pass the untouched image
    x1, y1, x2, y2 = dets.bboxes[0].astype(int)
    assert np.all(fake.calls[1][y1 + 5:y2 - 5, x1 + 5:x2 - 5] == 128)
    assert np.all(fake.calls[0] == 200)
    np.testing.assert_allclose(dets.scores, [0.9, 0.7])
    for k, (world, R, t, _) in enumerate(people):
        # kpts3d = the world landmarks moved into the camera frame, exactly (noise-free PnP)
        np.testing.assert_allclose(dets.kpts3d[k], world @ R.T + t, atol=1e-6)
        uv = dets.kpts3d[k][:, :2] / dets.kpts3d[k][:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
        np.testing.assert_allclose(uv, dets.kpts2d[k], atol=1e-6)
    dets.validate(["cam0"])
    assert est.stats["detections"] == 2 and est.stats["passes"] == 3


def test_duplicates_small_people_and_convention():
    cam = _camera()
    same = (_body(0), _rot(0.0), np.array([0.0, 0.0, 4.0]), np.full(33, 0.9))
    far = (_body(2), _rot(0.0), np.array([-6.0, 0.0, 30.0]), np.full(33, 0.9))
    fake = ScriptedPose([same, same, far], cam)
    est = make_estimator("mediapipe", {"pose_factory": lambda o: fake, "min_bbox_height": 60,
                                       "keypoint_convention": "coco_17"}, Rig([cam]))
    dets = est.estimate(cam, 0, np.zeros((480, 640, 3), np.uint8))
    assert dets.n == 1 and dets.num_joints == 17
    assert est.stats["dropped_duplicate"] == 1 and est.stats["dropped_small"] == 1


def test_low_visibility_landmarks_are_nan_and_cross_the_wire():
    """min_visibility: landmarks BlazePose is less sure of are NaN (not seen) in kpts2d, still
    placed in 3D (kpts3d stays the whole body), and the detections message carries them."""
    from maem_ros.ros import wire
    cam = _camera()
    vis = np.full(33, 0.95)
    vis[[15, 16, 27]] = [0.3, 0.79, 0.1]  # both wrists, the left ankle
    people = [(_body(0), _rot(0.2), np.array([0.0, 0.1, 4.0]), vis)]
    est = make_estimator("mediapipe", {"pose_factory": lambda o: ScriptedPose(people, cam),
                                       "min_visibility": 0.8}, Rig([cam]))
    dets = est.estimate(cam, 7, np.full((480, 640, 3), 200, np.uint8)).validate(["cam0"])
    unseen = np.isnan(dets.kpts2d[0]).any(-1)
    np.testing.assert_array_equal(np.flatnonzero(unseen), [15, 16, 27])
    assert np.isfinite(dets.kpts3d).all()
    for layout in ("f32", "q4"):
        back = wire.msg_to_detections(wire.detections_to_msg(dets, keypoints=layout), "/cam0/d")
        np.testing.assert_array_equal(np.isnan(back.kpts2d[0]).any(-1), unseen)
        np.testing.assert_allclose(back.kpts2d[0][~unseen], dets.kpts2d[0][~unseen], atol=1 / 16)
    with pytest.raises(ValueError, match="'min_visibility': must be in"):
        make_estimator("mediapipe", {"pose_factory": lambda o: None, "min_visibility": 1.5},
                       Rig([cam]))


def test_bad_image_and_options():
    cam = _camera()
    est = make_estimator("mediapipe", {"pose_factory": lambda o: ScriptedPose([], cam)}, Rig([cam]))
    with pytest.raises(ValueError, match="camera 'cam0': expected a BGR uint8"):
        est.estimate(cam, 0, np.zeros((480, 640), np.uint8))
    empty = est.estimate(cam, 0, np.zeros((480, 640, 3), np.uint8))
    assert empty.n == 0 and empty.num_joints == 33
    with pytest.raises(ValueError, match="'mask_threshold': must be in"):
        make_estimator("mediapipe", {"pose_factory": lambda o: None, "mask_threshold": 2},
                       Rig([cam]))
    with pytest.raises(ValueError, match="mhr70"):
        make_estimator("mediapipe", {"pose_factory": lambda o: None,
                                     "keypoint_convention": "mhr70"}, Rig([cam]))


def test_missing_wheel_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # import fails as if not installed
    with pytest.raises(ImportError) as e:
        import_mediapipe()
    assert "pip install --no-deps mediapipe==0.10.21" in str(e.value)
    assert str(e.value).startswith(INSTALL_HELP)


# ---- real footage ----------------------------------------------------------------------------
def _first_frames(demo_dir, rig: Rig, frame: int = 0) -> dict[str, np.ndarray]:
    out = {}
    for cam in rig:
        cap = cv2.VideoCapture(str(demo_dir / "videos" / f"{cam.name}.mp4"))
        cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
        ok, img = cap.read()
        cap.release()
        assert ok, f"{cam.name}: frame {frame} not decodable"
        out[cam.name] = Rectifier(cam).rectify(img)
    return out


def test_real_frames_two_people_triangulated(pose2sim_demo, mediapipe_installed):
    """Frame 0 of the four real cameras: both people found in every view, associated on
    keypoints only and triangulated standing on the lab floor (z up, metres), in a few px."""
    rig = Rig.load(pose2sim_demo / "calibration" / "Calib.qca.txt")
    images = _first_frames(pose2sim_demo, rig)
    frames = {}
    for cam in rig:
        est = make_estimator("mediapipe", load_node_params("mediapipe.yaml", "frontend"), rig)
        frames[cam.name] = est.estimate(cam, 0, images[cam.name]).validate(rig.names)
        assert frames[cam.name].n == 2, cam.name
    assoc = AssociationParams.from_mapping(load_node_params("mediapipe.yaml", "association"))
    tri = TriangulationParams.from_mapping(load_node_params("mediapipe.yaml", "triangulation"))
    result = associate(rig, frames, assoc)
    poses = triangulate(rig, frames, result.clusters, tri)
    assert len(poses) == 2
    sc = convert(poses.joints, SPORTCENTER_13, BLAZEPOSE_33.name)
    hips = np.nanmean(sc[:, 7:9], axis=1)
    ankles = np.nanmean(sc[:, 11:13], axis=1)
    assert np.all((hips[:, 2] > 0.6) & (hips[:, 2] < 1.4)), hips  # hip height above the floor
    assert np.all(np.abs(ankles[:, 2] - 0.1) < 0.25), ankles
    assert np.linalg.norm(hips[0, :2] - hips[1, :2]) > 0.4  # two people, not one twice
    # reprojection of the triangulated joints into the views that kept them
    errs = []
    for cl, X in zip(result.clusters, poses.joints):
        for c, d in cl.members:
            e = np.linalg.norm(rig[int(c)].project_rectified(X) - frames[rig.names[c]].kpts2d[d], axis=1)
            errs.append(e[np.isfinite(e)])
    errs = np.concatenate(errs)
    assert np.mean(errs[errs < tri.tau_kps]) < 8.0
    assert np.median(errs) < 10.0


def test_mediapipe_convention_in_config():
    fe = load_node_params("mediapipe.yaml", "frontend")
    assert fe["backend"] == "mediapipe"
    assert get_convention(fe["keypoint_convention"]) is BLAZEPOSE_33
    assert load_node_params("mediapipe.yaml", "association")["epipolar_gate"] == "sparse"
