"""sam3d_body backend against a stand-in written from the official SAM 3D Body output contract.

The stand-in follows facebookresearch/sam-3d-body ``SAM3DBodyEstimator.process_one_image``:
numpy images are RGB; ``cam_int`` is a (1,3,3) float tensor (default when None: focal
sqrt(h^2 + w^2), principal point at the image centre); per person a dict with ``bbox`` (the input
box), ``pred_vertices`` / ``pred_keypoints_3d`` (metres, OpenCV camera axes, relative to
``pred_cam_t``), ``pred_cam_t`` (camera-frame translation), ``pred_keypoints_2d`` = cam_int
projection of pred_keypoints_3d + pred_cam_t, ``focal_length``; some builds add ``bbox_score`` and
``pred_keypoints_2d_verts``. Its people are known 3D bodies in front of a known camera, so the
published 2D must land exactly where ``camera.project_rectified`` puts them.
"""
from __future__ import annotations

import sys
import types

import cv2
import numpy as np
import pytest
import torch

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.frontend.base import make_estimator
from maem_ros.frontend.rectify import Rectifier
from maem_ros.frontend.sam3d_body import (INSTALL_HELP, MHR_NUM_VERTICES, Sam3dBodyEstimator,
                                          project_camera_points)

W, H, V = 640, 480, 300


def _camera() -> Camera:
    R, _ = cv2.Rodrigues(np.array([0.15, -0.4, 0.05]))
    return Camera("cam_a", [[520.0, 0, 322.0], [0, 515.0, 238.0], [0, 0, 1]], R, [0.3, -0.2, 1.0],
                  W, H, "plumb_bob", [-0.22, 0.06, 0.001, -0.0015, -0.005],
                  K_rect=[[470.0, 0, 318.0], [0, 470.0, 242.0], [0, 0, 1]])


def _bodies(camera: Camera, centres_cam=((-0.9, 0.1, 6.0), (1.0, -0.1, 7.5))):
    """World-frame vertices (P,V,3) and MHR70 keypoints (P,70,3) of people at camera-frame centres."""
    rng = np.random.default_rng(3)
    size = np.array([0.5, 1.7, 0.3])
    verts, kpts = [], []
    for c in centres_cam:
        v = np.asarray(c) + (rng.random((V, 3)) - 0.5) * size
        k = np.asarray(c) + (rng.random((70, 3)) - 0.5) * size * 0.9
        verts.append((v - camera.t) @ camera.R)  # camera -> world: R^T (X - t)
        kpts.append((k - camera.t) @ camera.R)
    return np.array(verts), np.array(kpts)


class OfficialStandIn:
    """process_one_image of the official estimator, on known geometry (see the module doc)."""

    def __init__(self, camera, verts_w, kpts_w, bbox_score=None, verts2d=False, verts2d_offset=0.0):
        self.R, self.t = camera.R, camera.t
        self.verts_w, self.kpts_w = verts_w, kpts_w
        self.bbox_score, self.verts2d, self.offset = bbox_score, verts2d, verts2d_offset
        self.calls: list[dict] = []

    def process_one_image(self, img, bboxes=None, masks=None, cam_int=None, det_cat_id=0,
                          bbox_thr=0.5, nms_thr=0.3, use_mask=False, inference_type="full"):
        h, w = img.shape[:2]
        if cam_int is None:
            f = (h ** 2 + w ** 2) ** 0.5
            K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
        else:
            assert isinstance(cam_int, torch.Tensor) and tuple(cam_int.shape) == (1, 3, 3)
            K = cam_int[0].double().numpy()
        self.calls.append(dict(img=img.copy(), K=K, bboxes=bboxes, bbox_thr=bbox_thr,
                               inference_type=inference_type,
                               autocast=torch.is_autocast_enabled("cpu")))
        vc = self.verts_w @ self.R.T + self.t
        kc = self.kpts_w @ self.R.T + self.t
        proj_boxes = []
        for p in range(len(vc)):
            uv = project_camera_points(vc[p], K)
            proj_boxes.append(np.r_[uv.min(0), uv.max(0)])
        proj_boxes = np.array(proj_boxes)
        if bboxes is None:
            picks, boxes = list(range(len(vc))), proj_boxes
        else:
            boxes = np.asarray(bboxes, np.float64).reshape(-1, 4)
            picks = [int(np.argmax([_iou(b, pb) for pb in proj_boxes])) for b in boxes]
        out = []
        for box, p in zip(boxes, picks):
            root = kc[p].mean(0)
            d = {"bbox": box.astype(np.float32), "focal_length": np.float32(K[0, 0]),
                 "pred_cam_t": root.astype(np.float32),
                 "pred_vertices": (vc[p] - root).astype(np.float32),
                 "pred_keypoints_3d": (kc[p] - root).astype(np.float32),
                 "pred_keypoints_2d": project_camera_points(kc[p], K).astype(np.float32)}
            if self.bbox_score is not None:
                d["bbox_score"] = np.float32(self.bbox_score[p])
            if self.verts2d:
                d["pred_keypoints_2d_verts"] = (project_camera_points(vc[p], K)
                                                + self.offset).astype(np.float32)
            out.append(d)
        return out


def _iou(a, b) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def _setup(scores=(0.95, 0.8), **standin_kw):
    cam = _camera()
    verts_w, kpts_w = _bodies(cam)
    standin = OfficialStandIn(cam, verts_w, kpts_w, **standin_kw)
    boxes = np.array([np.r_[uv.min(0), uv.max(0)] for uv in cam.project_rectified(verts_w)])

    def detector_factory(options, model):
        assert model is standin
        return lambda img: (boxes + 0.5, np.asarray(scores))  # slightly off boxes, like a detector
    return cam, verts_w, kpts_w, standin, boxes, detector_factory


def _raw_image(cam: Camera) -> np.ndarray:
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (0, 0), 3)
    img[..., 2] = 230  # red channel constant: the model must receive it first (RGB)
    return img


def test_projected_vertices_land_where_the_camera_puts_them():
    cam, verts_w, kpts_w, standin, boxes, det = _setup()
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector_factory": det,
                              "bbox_thr": 0.3, "rectify": True}, Rig([cam]))
    raw = _raw_image(cam)
    dets = est.estimate(cam, 42, raw)
    assert dets.camera == "cam_a" and dets.stamp_ns == 42 and dets.n == 2
    dets.validate()
    # published 2D = the rig camera's rectified projection of the known bodies
    assert np.abs(dets.verts2d - cam.project_rectified(verts_w)).max() < 1e-3
    assert np.abs(dets.kpts2d - cam.project_rectified(kpts_w)).max() < 1e-3
    assert dets.verts2d.shape == (2, V, 2) and dets.kpts2d.shape == (2, 70, 2)
    # 3D keypoints: camera-relative metres (root-relative), the official pred_keypoints_3d
    kc = kpts_w @ cam.R.T + cam.t
    assert np.allclose(dets.kpts3d, kc - kc.mean(1, keepdims=True), atol=1e-5)
    assert np.allclose(dets.scores, [0.95, 0.8]) and np.allclose(dets.bboxes, boxes + 0.5)
    call = standin.calls[-1]
    assert np.allclose(call["K"], cam.K_rect), "cam_int must be the rig's K_rect"
    assert np.allclose(call["bboxes"], boxes + 0.5) and call["bbox_thr"] == 0.3
    # the model got the RECTIFIED image in RGB order
    expected = cv2.cvtColor(Rectifier(cam).rectify(raw), cv2.COLOR_BGR2RGB)
    assert np.array_equal(call["img"], expected)
    assert not np.array_equal(call["img"], raw[..., ::-1]), "image was not rectified"
    assert call["inference_type"] == "full" and not call["autocast"]
    assert est.stats["detections"] == 2 and est.stats["vertex_mismatch"] == 0


def test_given_vertex_projections_are_checked():
    cam, verts_w, _, standin, _, det = _setup(verts2d=True)
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector_factory": det},
                             Rig([cam]))
    dets = est.estimate(cam, 1, _raw_image(cam))
    assert est.stats["vertex_mismatch"] == 0 and est.stats["max_vertex_disagreement_px"] < 1e-3
    standin.offset = np.array([4.0, -3.0])  # a build whose projections disagree by 5 px
    dets = est.estimate(cam, 2, _raw_image(cam))
    assert est.stats["vertex_mismatch"] == 2
    assert est.stats["max_vertex_disagreement_px"] == pytest.approx(5.0, abs=1e-3)
    # the build's own projections are what gets published
    assert np.allclose(dets.verts2d, cam.project_rectified(verts_w) + [4.0, -3.0], atol=1e-3)


def test_convention_bbox_score_precision_and_stride():
    cam, _, kpts_w, standin, _, det = _setup(bbox_score=(0.6, 0.99))
    opts = {"estimator_factory": lambda o: standin, "detector_factory": det,
            "keypoint_convention": "sportcenter_13", "precision": "bf16", "device": "cpu",
            "inference_type": "body", "vertex_stride": 3}
    est = make_estimator("sam3d_body", opts, Rig([cam]))
    dets = est.estimate(cam, 5, _raw_image(cam))
    assert dets.kpts2d.shape == (2, 13, 2) and dets.kpts3d.shape == (2, 13, 3)
    assert np.abs(dets.kpts2d - SPORTCENTER_13.select(cam.project_rectified(kpts_w))).max() < 1e-3
    assert np.allclose(dets.scores, [0.6, 0.99])  # the build's bbox_score wins over the detector's
    assert dets.verts2d.shape == (2, (V + 2) // 3, 2)
    assert standin.calls[-1]["autocast"] and standin.calls[-1]["inference_type"] == "body"


def test_detector_none_and_model_modes():
    cam, verts_w, _, standin, _, _ = _setup()
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector": "none"}, Rig([cam]))
    dets = est.estimate(cam, 3, _raw_image(cam))
    assert np.allclose(standin.calls[-1]["bboxes"], [[0, 0, W, H]])
    assert dets.n == 1 and dets.scores[0] == 1.0
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector": "model"},
                             Rig([cam]))
    dets = est.estimate(cam, 4, _raw_image(cam))
    assert standin.calls[-1]["bboxes"] is None and dets.n == 2  # the estimator's own boxes
    assert np.abs(dets.verts2d - cam.project_rectified(verts_w)).max() < 1e-3


def test_empty_invalid_and_bad_input():
    cam, verts_w, kpts_w, standin, boxes, _ = _setup()
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin,
                              "detector_factory": lambda o, m: (lambda img: (np.zeros((0, 4)),
                                                                             np.zeros(0)))},
                             Rig([cam]))
    dets = est.estimate(cam, 9, _raw_image(cam))
    assert dets.n == 0 and dets.num_vertices == MHR_NUM_VERTICES and dets.num_joints == 70
    assert not standin.calls, "no boxes: the model is not run"
    # a body partly behind the camera is dropped and counted
    behind_cam = np.array([0.0, 0.0, 0.05]) + (np.random.default_rng(1).random((V, 3)) - 0.5)
    standin.verts_w = np.concatenate([verts_w, ((behind_cam - cam.t) @ cam.R)[None]])
    standin.kpts_w = np.concatenate([kpts_w, kpts_w[:1]])
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector": "model"},
                             Rig([cam]))
    dets = est.estimate(cam, 10, _raw_image(cam))
    assert dets.n == 2 and est.stats["dropped_invalid"] == 1
    dets.validate()
    with pytest.raises(ValueError, match="expected a BGR uint8"):
        est.estimate(cam, 1, np.zeros((H, W), np.uint8))
    with pytest.raises(ValueError, match="image is 320x240 but the rig calibration is 640x480"):
        est.estimate(cam, 1, np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(ValueError, match="'precision': unknown 'fp8'"):
        Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "precision": "fp8"}, Rig([cam]))
    with pytest.raises(ValueError, match="'device'"):
        Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "device": "tpu"}, Rig([cam]))


def test_rectified_input_is_not_rectified_again():
    cam, verts_w, _, standin, _, det = _setup()
    est = Sam3dBodyEstimator({"estimator_factory": lambda o: standin, "detector_factory": det},
                             Rig([cam]))
    img = _raw_image(cam)
    est.estimate(cam, 1, img)
    assert np.array_equal(standin.calls[-1]["img"], img[..., ::-1])


def test_missing_package_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "sam_3d_body", None)  # import fails like an absent package
    with pytest.raises(ImportError) as e:
        make_estimator("sam3d_body", {"checkpoint_path": "/x/model.ckpt", "detector": "none"},
                       Rig([_camera()]))
    msg = str(e.value)
    assert "git clone https://github.com/facebookresearch/sam-3d-body" in msg
    assert "hf download facebook/sam-3d-body-dinov3" in msg and "mhr_model.pt" in msg
    assert INSTALL_HELP in msg
    with pytest.raises(ValueError, match="'repo_path'.*no sam_3d_body"):
        Sam3dBodyEstimator({"repo_path": "/nonexistent", "detector": "none"}, Rig([_camera()]))


def test_official_construction_path(monkeypatch, tmp_path):
    """build_official_estimator calls the official API: load_sam_3d_body + SAM3DBodyEstimator."""
    calls = {}
    cam, verts_w, kpts_w, standin, _, _ = _setup()

    def load_sam_3d_body(checkpoint_path, device="cuda", mhr_path=""):
        calls["load"] = (checkpoint_path, device, mhr_path)
        return "MODEL", "CFG"

    class SAM3DBodyEstimator:
        def __init__(self, sam_3d_body_model, model_cfg, human_detector=None, human_segmentor=None,
                     fov_estimator=None):
            calls["est"] = (sam_3d_body_model, model_cfg, human_detector, fov_estimator)
            self.detector = human_detector

        process_one_image = standin.process_one_image

    fake = types.ModuleType("sam_3d_body")
    fake.load_sam_3d_body, fake.SAM3DBodyEstimator = load_sam_3d_body, SAM3DBodyEstimator
    monkeypatch.setitem(sys.modules, "sam_3d_body", fake)
    ckpt = tmp_path / "model.ckpt"
    opts = {"checkpoint_path": str(ckpt), "detector": "none", "device": "cpu"}
    with pytest.raises(ValueError, match="'checkpoint_path'.*does not exist"):
        Sam3dBodyEstimator(opts, Rig([cam]))
    ckpt.write_bytes(b"x")
    with pytest.raises(ValueError, match="'mhr_path'.*assets/mhr_model.pt"):
        Sam3dBodyEstimator(opts, Rig([cam]))
    (tmp_path / "assets").mkdir()
    (tmp_path / "assets" / "mhr_model.pt").write_bytes(b"x")
    est = Sam3dBodyEstimator(opts, Rig([cam]))
    assert calls["load"] == (str(ckpt), "cpu", str(tmp_path / "assets" / "mhr_model.pt"))
    assert calls["est"] == ("MODEL", "CFG", None, None)
    dets = est.estimate(cam, 7, _raw_image(cam))
    assert dets.n == 1
    with pytest.raises(ValueError, match="'checkpoint_path': required"):
        Sam3dBodyEstimator({"detector": "none"}, Rig([cam]))
