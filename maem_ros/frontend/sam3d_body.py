"""sam3d_body backend: the official SAM 3D Body model (facebookresearch/sam-3d-body) per image.

Per frame (the frontend node passes the RECTIFIED image; with option ``rectify`` the raw
image is rectified here with a Rectifier whose maps are cached per camera): detect people
(official ViTDet ``HumanDetector``, keeping the detection scores), run
``SAM3DBodyEstimator.process_one_image(rgb, bboxes=..., cam_int=K_rect)`` so the model
projects with the rig's rectified intrinsics, then per person:

* bbox (x1 y1 x2 y2 rectified px), score = the build's ``bbox_score`` if it returns one, else
  the detector's score;
* kpts3d = ``pred_keypoints_3d`` (MHR70, metres, OpenCV camera axes, relative to
  ``pred_cam_t``), kpts2d = ``pred_keypoints_2d`` (rectified px), both reduced to the
  configured keypoint convention;
* verts2d = K_rect-projection of ``pred_vertices + pred_cam_t`` (camera frame, metres), batched
  over people; when the build also returns ``pred_keypoints_2d_verts`` those are published and the
  two are compared (disagreement > ``vertex_check_tol`` px is counted in ``stats`` and logged once).

Install (GPU machine; not installable offline): clone https://github.com/facebookresearch/sam-3d-body,
follow its INSTALL.md (PyTorch + CUDA, its pip dependencies, detectron2 from
``git+https://github.com/facebookresearch/detectron2.git@a1ce2f9`` for the ViTDet detector), request
access to the gated weights on Hugging Face and ``hf download facebook/sam-3d-body-dinov3
--local-dir checkpoints/sam-3d-body-dinov3``.

Options (frontend parameters; unknown keys are ignored):
  checkpoint_path   .../model.ckpt (model_config.yaml next to it or one folder up); required
                    unless hf_repo_id is given
  mhr_path          .../assets/mhr_model.pt (default: assets/mhr_model.pt next to the checkpoint)
  hf_repo_id        download with the official load_sam_3d_body_hf instead (e.g.
                    facebook/sam-3d-body-dinov3; needs Hugging Face access)
  repo_path         the sam-3d-body clone (put on sys.path: its ``sam_3d_body`` package and
                    ``tools/build_detector.py``)
  device            auto | cpu | cuda | cuda:N (default auto)
  precision         fp32 | fp16 | bf16 (autocast around the model; default fp32)
  detector          vitdet (official ViTDet, scores kept) | model (the estimator's own detector;
                    score = bbox_score or 1.0) | none (whole image = one person, score 1.0)
  bbox_thr          detector score threshold (default 0.5, the official default)
  inference_type    full (body + hand decoders) | body (faster)
  keypoint_convention  mhr70 | sportcenter_13 | coco_17 (default mhr70)
  vertex_check_tol  px (default 2.0)
  rectify           true: estimate() gets RAW images and rectifies them here; false (default):
                    it gets the rectified image (what the frontend node passes)
  estimator_factory callable(options) -> object with the official process_one_image signature
  detector_factory  callable(options, estimator) -> callable(bgr image) -> (boxes (N,4), scores (N,))
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.skeleton import KeypointConvention, get_convention

from .base import Estimator, check_bgr_image, option_float
from .rectify import Rectifier

log = logging.getLogger(__name__)

#: vertices of the MHR mesh (fixed topology) used for empty frames before the first output
MHR_NUM_VERTICES = 18439
MHR_NUM_KEYPOINTS = 70

INSTALL_HELP = (
    "install the official SAM 3D Body package on this machine: git clone "
    "https://github.com/facebookresearch/sam-3d-body, follow its INSTALL.md (PyTorch with CUDA, "
    "its pip dependencies, and for the ViTDet detector: pip install "
    "'git+https://github.com/facebookresearch/detectron2.git@a1ce2f9'), then set the frontend "
    "option repo_path to the clone. Weights (gated, request access on Hugging Face first): "
    "hf download facebook/sam-3d-body-dinov3 --local-dir checkpoints/sam-3d-body-dinov3, then "
    "checkpoint_path=checkpoints/sam-3d-body-dinov3/model.ckpt and "
    "mhr_path=checkpoints/sam-3d-body-dinov3/assets/mhr_model.pt"
)

Detector = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def project_camera_points(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(...,3) camera-frame metres -> (...,2) px with intrinsics K; NaN for z <= 0."""
    X = np.asarray(X, dtype=np.float64)
    z = X[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (X[..., :2] / z) @ K[:2, :2].T + K[:2, 2]
    return np.where(z > 1e-9, uv, np.nan)


def _choice(options: Mapping[str, Any], key: str, default: str, choices: Sequence[str]) -> str:
    value = str(options.get(key, default) or default).strip().lower()
    if value not in choices:
        raise ValueError(f"frontend option {key!r}: unknown {value!r}, expected one of {list(choices)}")
    return value


def _bool(options: Mapping[str, Any], key: str, default: bool) -> bool:
    value = options.get(key, default)
    if isinstance(value, str) and value.lower() in ("true", "false", "1", "0"):
        return value.lower() in ("true", "1")
    if not isinstance(value, (bool, int, np.bool_)):
        raise ValueError(f"frontend option {key!r}: expected true/false, got {value!r}")
    return bool(value)


class Sam3dBodyEstimator(Estimator):
    """SAM 3D Body on each (rectified) image of a camera -> FrameDetections in rectified px."""

    needs_image = True

    def __init__(self, options: Mapping[str, Any], rig: Rig):
        options = dict(options or {})
        self.rig = rig
        self.device = _choice_device(options.get("device", "auto"))
        self.precision = _choice(options, "precision", "fp32", ("fp32", "fp16", "bf16"))
        self.detector_mode = _choice(options, "detector", "vitdet", ("vitdet", "model", "none"))
        self.inference_type = _choice(options, "inference_type", "full", ("full", "body"))
        self.bbox_thr = option_float(options, "bbox_thr", 0.5)
        if not 0.0 <= self.bbox_thr <= 1.0:
            raise ValueError(f"frontend option 'bbox_thr': must be in [0, 1], got {self.bbox_thr}")
        self.vertex_check_tol = option_float(options, "vertex_check_tol", 2.0, positive=True)
        self.convention: KeypointConvention = get_convention(
            str(options.get("keypoint_convention", "mhr70") or "mhr70")
        )
        self.rectify = _bool(options, "rectify", False)
        factory = options.get("estimator_factory")
        if factory is not None and not callable(factory):
            raise ValueError("frontend option 'estimator_factory': expected a callable")
        self.model = (
            factory(options)
            if factory is not None
            else build_official_estimator(options, self.device, self.detector_mode)
        )
        if not callable(getattr(self.model, "process_one_image", None)):
            raise ValueError("sam3d_body backend: the estimator has no process_one_image()")
        self.detect = self._make_detector(options)
        self._rectifiers: dict[str, Rectifier] = {}
        self._num_vertices = MHR_NUM_VERTICES
        self._warned: set[str] = set()
        #: counters: frames, detections, dropped_invalid, vertex_mismatch (detections),
        #: max_vertex_disagreement_px (worst seen)
        self.stats: dict[str, float] = dict(
            frames=0, detections=0, dropped_invalid=0, vertex_mismatch=0, max_vertex_disagreement_px=0.0
        )

    # ---- construction helpers -------------------------------------------------------------
    def _make_detector(self, options: Mapping[str, Any]) -> Detector | None:
        factory = options.get("detector_factory")
        if factory is not None:
            if not callable(factory):
                raise ValueError("frontend option 'detector_factory': expected a callable")
            return factory(options, self.model)
        if self.detector_mode != "vitdet":
            return None
        human_detector = getattr(self.model, "detector", None)
        if human_detector is None or not hasattr(human_detector, "detector"):
            raise ValueError(
                "sam3d_body backend: detector=vitdet needs the official ViTDet "
                "HumanDetector (tools/build_detector.py in the sam-3d-body clone; "
                "set repo_path) or another detector option (model | none)"
            )
        return vitdet_with_scores(human_detector.detector, self.bbox_thr)

    def rectifier(self, camera: Camera) -> Rectifier:
        r = self._rectifiers.get(camera.name)
        if r is None or r.camera is not camera:
            r = self._rectifiers[camera.name] = Rectifier(camera)
        return r

    # ---- per frame ------------------------------------------------------------------------
    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None) -> FrameDetections:
        """Rectified BGR uint8 (H,W,3) image (raw with option ``rectify``) -> detections."""
        image = check_bgr_image(image, "sam3d_body", camera.name)
        rect = self.rectifier(camera)
        if self.rectify:
            image = rect.rectify(image)
        else:
            rect.check_size(image)
        return self.estimate_rectified(camera, stamp_ns, image)

    def estimate_rectified(self, camera: Camera, stamp_ns: int, image_bgr: np.ndarray) -> FrameDetections:
        """Run the model on a rectified BGR image of ``camera`` (size = calibration)."""
        self.stats["frames"] += 1
        boxes, scores = self._boxes(image_bgr)
        if boxes is not None and len(boxes) == 0:
            return self._empty(camera, stamp_ns)
        rgb = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2RGB)  # numpy input is taken as RGB
        with self._autocast():
            outputs = self.model.process_one_image(
                rgb,
                bboxes=boxes,
                cam_int=self._cam_int(camera),
                bbox_thr=self.bbox_thr,
                inference_type=self.inference_type,
            )
        outputs = list(outputs or [])
        if boxes is not None and len(outputs) != len(boxes):
            raise ValueError(f"sam3d_body backend: {len(outputs)} outputs for {len(boxes)} boxes")
        if not outputs:
            return self._empty(camera, stamp_ns)
        return self.outputs_to_detections(outputs, camera, stamp_ns, scores)

    def _boxes(self, image_bgr: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self.detect is not None:
            boxes, scores = self.detect(image_bgr)
            boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
            scores = np.asarray(scores, dtype=np.float64).ravel()
            if scores.shape[0] != boxes.shape[0]:
                raise ValueError(
                    f"sam3d_body backend: detector gave {boxes.shape[0]} boxes and {scores.shape[0]} scores"
                )
            return boxes, scores
        if self.detector_mode == "none":
            h, w = image_bgr.shape[:2]
            return np.array([[0, 0, w, h]], np.float32), np.ones(1)
        return None, None  # the estimator's own detector decides the boxes

    def _cam_int(self, camera: Camera):
        """K_rect as the official cam_int: a float32 torch tensor (1,3,3) (numpy without torch)."""
        K = camera.K_rect[None].astype(np.float32)
        try:
            import torch
        except ImportError:
            return K
        return torch.from_numpy(K)

    def _autocast(self):
        if self.precision == "fp32":
            return contextlib.nullcontext()
        import torch

        dtype = torch.float16 if self.precision == "fp16" else torch.bfloat16
        return torch.autocast(device_type=self.device.split(":")[0], dtype=dtype)

    def _empty(self, camera: Camera, stamp_ns: int) -> FrameDetections:
        return FrameDetections.empty(camera.name, stamp_ns, self.convention.num_joints, self._num_vertices)

    # ---- outputs -> FrameDetections ---------------------------------------------------------
    def outputs_to_detections(
        self,
        outputs: Sequence[Mapping[str, Any]],
        camera: Camera,
        stamp_ns: int,
        det_scores: np.ndarray | None = None,
    ) -> FrameDetections:
        """Official per-person dicts (rectified px, K_rect) -> FrameDetections (drops invalid)."""
        where = f"sam3d_body output of camera {camera.name!r}"
        bboxes = np.stack([_arr(o, "bbox", (4,), where) for o in outputs])
        kp3d = np.stack([_arr(o, "pred_keypoints_3d", (MHR_NUM_KEYPOINTS, 3), where) for o in outputs])
        kp2d = np.stack([_arr(o, "pred_keypoints_2d", (MHR_NUM_KEYPOINTS, 2), where) for o in outputs])
        verts = np.stack([_arr(o, "pred_vertices", (None, 3), where) for o in outputs])
        cam_t = np.stack([_arr(o, "pred_cam_t", (3,), where) for o in outputs])
        scores = np.array(
            [
                float(np.asarray(o["bbox_score"]).ravel()[0])
                if "bbox_score" in o
                else (det_scores[i] if det_scores is not None else 1.0)
                for i, o in enumerate(outputs)
            ]
        )
        if det_scores is None and not any("bbox_score" in o for o in outputs):
            self._warn_once(
                "score",
                "sam3d_body: this build returns no bbox_score and no "
                "detector score is available: scores are 1.0, tau_det "
                "cannot filter",
            )
        verts2d = project_camera_points(verts + cam_t[:, None, :], camera.K_rect)
        if all("pred_keypoints_2d_verts" in o for o in outputs):
            verts2d = self._check_given_vertices(outputs, verts2d, where)
        self._num_vertices = verts.shape[1]
        valid = (
            np.all(np.isfinite(verts2d), axis=(1, 2))
            & np.all(np.isfinite(kp2d), axis=(1, 2))
            & np.all(np.isfinite(kp3d), axis=(1, 2))
            & np.all(np.isfinite(bboxes), axis=1)
            & np.isfinite(scores)
            & (bboxes[:, 2] >= bboxes[:, 0])
            & (bboxes[:, 3] >= bboxes[:, 1])
        )
        if not valid.all():
            self.stats["dropped_invalid"] += int((~valid).sum())
            self._warn_once(
                "invalid",
                f"{where}: dropped {int((~valid).sum())} detection(s) with "
                "non-finite values or points behind the camera",
            )
        self.stats["detections"] += int(valid.sum())
        conv = self.convention
        dets = FrameDetections(
            camera.name,
            stamp_ns,
            bboxes,
            np.clip(scores, 0.0, 1.0),
            conv.select(kp2d),
            conv.select(kp3d),
            verts2d.astype(np.float32),
        )
        return dets.select(valid) if not valid.all() else dets

    def _check_given_vertices(self, outputs, computed: np.ndarray, where: str) -> np.ndarray:
        given = np.stack([_arr(o, "pred_keypoints_2d_verts", (computed.shape[1], 2), where) for o in outputs])
        with np.errstate(invalid="ignore"):
            err = np.nanmax(np.linalg.norm(given - computed, axis=2), axis=1)
        err = np.where(np.isfinite(err), err, np.inf)
        bad = err > self.vertex_check_tol
        self.stats["max_vertex_disagreement_px"] = max(
            self.stats["max_vertex_disagreement_px"], float(np.max(err))
        )
        if bad.any():
            self.stats["vertex_mismatch"] += int(bad.sum())
            self._warn_once(
                "verts",
                f"{where}: pred_keypoints_2d_verts differ from the K_rect "
                f"projection of pred_vertices + pred_cam_t by up to "
                f"{float(np.max(err)):.1f} px (> {self.vertex_check_tol} px); "
                "check that cam_int reaches the model",
            )
        return given

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(message)


def _arr(output: Mapping[str, Any], key: str, shape: tuple[int | None, ...], where: str) -> np.ndarray:
    if key not in output:
        raise ValueError(f"{where}: missing {key!r}")
    value = output[key]
    if hasattr(value, "detach"):  # a torch tensor from a custom build
        value = value.detach().float().cpu().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "(" + ",".join("V" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{where}: {key}: expected shape {want}, got {arr.shape}")
    return arr


def _choice_device(value: Any) -> str:
    device = str(value or "auto").strip().lower()
    if device == "auto":
        try:
            import torch

            return "cuda" if torch.cuda.is_available() else "cpu"
        except ImportError:
            return "cpu"
    if device != "cpu" and not (device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())):
        raise ValueError(f"frontend option 'device': unknown {device!r}, expected auto, cpu, cuda or cuda:N")
    return device


# ---- official model construction ------------------------------------------------------------
def _import_official(repo_path: str | None):
    if repo_path:
        root = Path(repo_path).expanduser()
        if not (root / "sam_3d_body").is_dir():
            raise ValueError(
                f"frontend option 'repo_path': {str(root)!r} has no sam_3d_body/ "
                "folder (expected a clone of facebookresearch/sam-3d-body)"
            )
        if str(root) not in sys.path:
            sys.path.insert(0, str(root))
    try:
        import sam_3d_body
    except ImportError as e:
        raise ImportError(
            f"sam3d_body backend: cannot import the official package ({e}); {INSTALL_HELP}"
        ) from None
    return sam_3d_body


def build_official_estimator(options: Mapping[str, Any], device: str, detector_mode: str):
    """The official SAM3DBodyEstimator: load_sam_3d_body(checkpoint, device, mhr_path) (or the
    Hugging Face loader), plus the ViTDet HumanDetector unless ``detector_mode`` is none."""
    sam_3d_body = _import_official(str(options.get("repo_path") or "") or None)
    hf_repo = str(options.get("hf_repo_id") or "")
    ckpt = str(options.get("checkpoint_path") or "")
    if hf_repo:
        model, model_cfg = sam_3d_body.load_sam_3d_body_hf(hf_repo, device=device)
    else:
        if not ckpt:
            raise ValueError(
                "frontend option 'checkpoint_path': required for the sam3d_body "
                f"backend (or hf_repo_id); {INSTALL_HELP}"
            )
        ckpt_path = Path(ckpt).expanduser()
        mhr = Path(str(options.get("mhr_path") or ckpt_path.parent / "assets" / "mhr_model.pt"))
        for what, p in (("checkpoint_path", ckpt_path), ("mhr_path", mhr.expanduser())):
            if not p.is_file():
                raise ValueError(f"frontend option {what!r}: {str(p)!r} does not exist; {INSTALL_HELP}")
        model, model_cfg = sam_3d_body.load_sam_3d_body(
            str(ckpt_path), device=device, mhr_path=str(mhr.expanduser())
        )
    human_detector = None
    if detector_mode in ("vitdet", "model"):
        try:
            from tools.build_detector import HumanDetector
        except ImportError as e:
            raise ImportError(
                f"sam3d_body backend: cannot import tools.build_detector from the "
                f"sam-3d-body clone ({e}); set repo_path to the clone and install "
                "detectron2, or use detector=none"
            ) from None
        human_detector = HumanDetector(name="vitdet", device=device)
    return sam_3d_body.SAM3DBodyEstimator(
        sam_3d_body_model=model,
        model_cfg=model_cfg,
        human_detector=human_detector,
        human_segmentor=None,
        fov_estimator=None,
    )


def vitdet_with_scores(vitdet_model, bbox_thr: float, det_cat_id: int = 0) -> Detector:
    """People boxes AND scores from the official detectron2 ViTDet model (the official
    run_human_detection drops the scores). Same preprocessing: BGR, shortest edge 1024."""
    import detectron2.data.transforms as T
    import torch

    resize = T.ResizeShortestEdge(short_edge_length=1024, max_size=1024)

    def detect(image_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = image_bgr.shape[:2]
        resized = resize(T.AugInput(image_bgr)).apply_image(image_bgr)
        tensor = torch.as_tensor(resized.astype("float32").transpose(2, 0, 1))
        with torch.no_grad():
            inst = vitdet_model([{"image": tensor, "height": h, "width": w}])[0]["instances"]
        keep = (inst.pred_classes == det_cat_id) & (inst.scores > bbox_thr)
        boxes = inst.pred_boxes.tensor[keep].cpu().numpy()
        scores = inst.scores[keep].cpu().numpy()
        order = np.lexsort((boxes[:, 3], boxes[:, 2], boxes[:, 1], boxes[:, 0]))
        return boxes[order], scores[order]

    return detect
