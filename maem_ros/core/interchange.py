"""MAEM interchange formats, read and write: SAM 3D Body npz, xrmocap GT, scene folders.

A scene folder (what ``maem-sim`` writes and ``maem-eval`` reads)::

    cameras/<view>.json          MAEM camera JSON (world->camera extrinsics, optional time_offset s),
                                 one per view (intrinsics only in a scene made for calibration)
    gt_rig.yaml                  optional (simulator): the true rig, extrinsics and time offsets
    dets/<view>/<frame:06d>.npz  SAM 3D Body outputs as the MAEM authors save them, RAW image px
    gt.npz                       xrmocap keypoints3d: pose (F,P,K,4) metres, mask (F,P,K), convention
    det_ids.npz                  optional: GT person of every detection, key "<view>/<frame:06d>",
                                 (N,) int64 in the npz's detection order, -1 = false positive
    images/<view>/<frame:06d>.jpg  optional raw (distorted) images
    scene.json                   optional: fps, start_stamp_ns, num_frames, scene_config (simulator)

Security note: the authors' npz stores ``outputs`` as a pickled object array, so reading one
needs ``allow_pickle=True``; only read npz files from sources you trust.
"""

from __future__ import annotations

import json
import os
import re
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.errors import InputError
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.sync import capture_stamp_ns, match_capture_times

#: keys every per-detection dict must hold (pred_cam_t and focal_length are optional)
REQUIRED_KEYS = ("bbox", "bbox_score", "pred_keypoints_3d", "pred_keypoints_2d", "pred_keypoints_2d_verts")
DEFAULT_FPS = 30.0


#: file of a scene folder with the GT person of every detection
DET_IDS = "det_ids.npz"


def det_ids_key(view: str, frame: int) -> str:
    """Key of one view and frame in det_ids.npz."""
    return f"{view}/{int(frame):06d}"


class MissingDataError(InputError):
    """A file a scene folder should hold is absent: a documented skip, not corruption."""

    reason = "no_data"


# ---- SAM 3D Body npz (MAEM authors' layout) -----------------------------------------------
def _field(d: Mapping, key: str, shape: tuple[int | None, ...], where: str) -> np.ndarray:
    """``d[key]`` as float64 of ``shape`` (None = any length), finite, else ValueError."""
    try:
        arr = np.asarray(d[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: field {key!r}: not numeric") from None
    if len(shape) == 1 and shape[0] is not None and arr.size == shape[0]:
        arr = arr.reshape(shape[0])  # bbox may be stored (1,4); a scalar may be stored (1,)
    if shape == () and arr.size == 1:
        arr = arr.reshape(())
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        want = (
            "("
            + ",".join("N" if s is None else str(s) for s in shape)
            + ("," if len(shape) == 1 else "")
            + ")"
        )
        raise ValueError(f"{where}: field {key!r}: expected shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: field {key!r}: contains NaN or inf")
    return arr


def validate_output(d: Any, where: str = "output") -> dict[str, np.ndarray]:
    """Check one SAM 3D Body output dict; return its fields as float64 arrays.

    ``where`` names the file and detection in the error message.
    """
    if not isinstance(d, Mapping):
        raise ValueError(f"{where}: expected a dict, got {type(d).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in d]
    if missing:
        raise ValueError(f"{where}: missing field(s) {', '.join(missing)}")
    out = {
        "bbox": _field(d, "bbox", (4,), where),
        "bbox_score": _field(d, "bbox_score", (), where),
        "pred_keypoints_3d": _field(d, "pred_keypoints_3d", (None, 3), where),
        "pred_keypoints_2d": _field(d, "pred_keypoints_2d", (None, 2), where),
        "pred_keypoints_2d_verts": _field(d, "pred_keypoints_2d_verts", (None, 2), where),
        "pred_cam_t": _field(d, "pred_cam_t", (3,), where) if "pred_cam_t" in d else np.zeros(3),
    }
    if "focal_length" in d:
        out["focal_length"] = np.asarray(d["focal_length"], dtype=np.float64)
    j3, j2 = out["pred_keypoints_3d"].shape[0], out["pred_keypoints_2d"].shape[0]
    if j3 != j2:
        raise ValueError(f"{where}: field 'pred_keypoints_2d': {j2} keypoints but pred_keypoints_3d has {j3}")
    x1, y1, x2, y2 = out["bbox"]
    if x2 < x1 or y2 < y1:
        raise ValueError(f"{where}: field 'bbox': inverted box {out['bbox'].tolist()}")
    if not 0.0 <= float(out["bbox_score"]) <= 1.0:
        raise ValueError(f"{where}: field 'bbox_score': {float(out['bbox_score'])} outside [0, 1]")
    return out


def read_maem_npz(path: str | Path) -> list[dict]:
    """Read a per-frame SAM 3D Body npz (``outputs`` object array of dicts), validating every dict."""
    path = Path(path)
    if not path.is_file():
        raise MissingDataError(f"npz {str(path)!r}: no such file")
    try:
        with np.load(path, allow_pickle=True) as z:
            files = list(z.files)
            raw = z["outputs"] if "outputs" in files else None
    except Exception as e:  # noqa: BLE001 - unpickling a corrupt file can raise nearly anything
        raise ValueError(f"npz {str(path)!r}: unreadable ({type(e).__name__}: {e})") from None
    if raw is None:
        raise ValueError(f"npz {str(path)!r}: no 'outputs' array (has {files})")
    if raw.dtype != object:
        if raw.size == 0:
            return []
        raise ValueError(
            f"npz {str(path)!r}: 'outputs' is a {raw.dtype} array, expected an object array of dicts"
        )
    items = raw.item() if raw.ndim == 0 else list(raw.ravel())
    if isinstance(items, Mapping):
        items = [items]
    if not isinstance(items, (list, tuple)):
        raise ValueError(f"npz {str(path)!r}: 'outputs' holds a {type(items).__name__}, expected dicts")
    for i, d in enumerate(items):
        validate_output(d, f"npz {str(path)!r} outputs[{i}]")
    return [dict(d) for d in items]


def write_maem_npz(
    path: str | Path, outputs: Sequence[Mapping], compress: bool = False, float32: bool = False
) -> None:
    """Write ``outputs`` (list of SAM 3D Body dicts) as the authors do; atomic (tmp file + rename).

    ``float32`` stores float arrays as float32, as the model emits them (half the bytes; 1e-4 px
    resolution at 2000 px).
    """
    path = Path(path)
    for i, d in enumerate(outputs):
        validate_output(d, f"write {str(path)!r} outputs[{i}]")
    arr = np.empty(len(outputs), dtype=object)
    for i, d in enumerate(outputs):
        arr[i] = {k: _stored(v, float32) for k, v in d.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    # a unique sibling opened with the normal umask (mkstemp would leave the file 0600)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "xb") as f:
            (np.savez_compressed if compress else np.savez)(f, outputs=arr)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _stored(value: Any, float32: bool) -> np.ndarray:
    arr = np.asarray(value)
    return arr.astype(np.float32) if float32 and arr.dtype.kind == "f" else arr


def outputs_to_detections(
    outputs: Sequence[Mapping],
    camera: Camera,
    stamp_ns: int,
    num_joints: int = 70,
    where: str = "outputs",
    vertex_stride: int = 1,
) -> FrameDetections:
    """SAM 3D Body outputs (RAW px) -> FrameDetections in the camera's RECTIFIED px.

    Keypoints, vertices and bbox centres of all people are undistorted in one batched call; each
    bbox keeps its width and height and is centred on its undistorted raw centre. kpts3d =
    pred_keypoints_3d + pred_cam_t (camera frame, metres). ``num_joints`` only sizes an empty frame.
    ``vertex_stride`` keeps every n-th vertex, dropped before undistortion (which dominates the cost).
    """
    if int(vertex_stride) < 1:
        raise ValueError(f"vertex_stride: must be >= 1, got {vertex_stride}")
    fields = [validate_output(d, f"{where}[{i}]") for i, d in enumerate(outputs)]
    if not fields:
        return FrameDetections.empty(camera.name, stamp_ns, num_joints, 0)
    j = fields[0]["pred_keypoints_2d"].shape[0]
    v = fields[0]["pred_keypoints_2d_verts"].shape[0]
    for i, f in enumerate(fields):
        if f["pred_keypoints_2d"].shape[0] != j or f["pred_keypoints_2d_verts"].shape[0] != v:
            raise ValueError(
                f"{where}[{i}]: {f['pred_keypoints_2d'].shape[0]} keypoints / "
                f"{f['pred_keypoints_2d_verts'].shape[0]} vertices, "
                f"but detection 0 has {j} / {v}"
            )
    bboxes = np.stack([f["bbox"] for f in fields])
    size = bboxes[:, 2:] - bboxes[:, :2]
    raw = np.concatenate(
        [
            0.5 * (bboxes[:, None, :2] + bboxes[:, None, 2:]),
            np.stack([f["pred_keypoints_2d"] for f in fields]),
            np.stack([f["pred_keypoints_2d_verts"][:: int(vertex_stride)] for f in fields]),
        ],
        axis=1,
    )
    rect = camera.undistort_points(raw)
    if not np.all(np.isfinite(rect)):
        bad = int(np.argwhere(~np.isfinite(rect))[0][0])
        raise ValueError(f"{where}[{bad}]: undistortion of camera {camera.name!r} gave NaN/inf")
    centre = rect[:, 0]
    return FrameDetections(
        camera=camera.name,
        stamp_ns=stamp_ns,
        bboxes=np.concatenate([centre - 0.5 * size, centre + 0.5 * size], axis=1),
        scores=np.array([float(f["bbox_score"]) for f in fields]),
        kpts2d=rect[:, 1 : 1 + j],
        kpts3d=np.stack([f["pred_keypoints_3d"] + f["pred_cam_t"] for f in fields]),
        verts2d=rect[:, 1 + j :].astype(np.float32),
        mesh_subset=(v, int(vertex_stride), 0) if int(vertex_stride) > 1 else None,
    )


def detections_to_outputs(dets: FrameDetections, camera: Camera) -> list[dict]:
    """Inverse of outputs_to_detections: rectified FrameDetections -> SAM 3D Body dicts in RAW px.

    pred_cam_t is the keypoint centroid and pred_keypoints_3d is relative to it (float32, as the
    model writes them).
    """
    if dets.n == 0:
        return []
    size = dets.bboxes[:, 2:] - dets.bboxes[:, :2]
    j = dets.num_joints
    rect = np.concatenate([dets.centers[:, None], dets.kpts2d, dets.verts2d.astype(np.float64)], axis=1)
    raw = camera.distort_points(rect)
    centre = raw[:, 0]
    cam_t = dets.kpts3d.mean(axis=1)
    focal = float(0.5 * (camera.K[0, 0] + camera.K[1, 1]))
    return [
        {
            "bbox": np.concatenate([centre[i] - 0.5 * size[i], centre[i] + 0.5 * size[i]]).astype(np.float32),
            "bbox_score": np.float32(dets.scores[i]),
            "pred_keypoints_3d": (dets.kpts3d[i] - cam_t[i]).astype(np.float32),
            "pred_keypoints_2d": raw[i, 1 : 1 + j].astype(np.float32),
            "pred_keypoints_2d_verts": raw[i, 1 + j :].astype(np.float32),
            "pred_cam_t": cam_t[i].astype(np.float32),
            "focal_length": np.float32(focal),
        }
        for i in range(dets.n)
    ]


# ---- xrmocap keypoints3d ground truth -------------------------------------------------------
def read_gt(path: str | Path) -> tuple[np.ndarray, np.ndarray, str]:
    """xrmocap keypoints3d npz -> (pose (F,P,K,4) metres, mask (F,P,K) bool, convention).

    Accepts ``pose`` or xrmocap's own ``keypoints`` key. Coordinates of masked-out joints are
    returned as NaN; a NaN/inf coordinate under a True mask is an error.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingDataError(f"gt {str(path)!r}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - zip/format errors come in many types
        raise ValueError(f"gt {str(path)!r}: unreadable ({type(e).__name__}: {e})") from None
    key = "pose" if "pose" in data else "keypoints" if "keypoints" in data else None
    if key is None or "mask" not in data:
        raise ValueError(f"gt {str(path)!r}: needs 'pose' (or 'keypoints') and 'mask', has {sorted(data)}")
    pose = np.asarray(data[key], dtype=np.float64)
    if pose.ndim != 4 or pose.shape[-1] not in (3, 4):
        raise ValueError(f"gt {str(path)!r}: field {key!r}: expected shape (F,P,K,4), got {pose.shape}")
    if pose.shape[-1] == 3:
        pose = np.concatenate([pose, np.ones(pose.shape[:-1] + (1,))], axis=-1)
    mask = np.asarray(data["mask"])
    if mask.shape != pose.shape[:3]:
        raise ValueError(f"gt {str(path)!r}: field 'mask': expected shape {pose.shape[:3]}, got {mask.shape}")
    mask = mask.astype(bool)
    bad = mask & ~np.all(np.isfinite(pose[..., :3]), axis=-1)
    if bad.any():
        f, p, k = np.argwhere(bad)[0]
        raise ValueError(
            f"gt {str(path)!r}: field {key!r}: NaN/inf at frame {f} person {p} joint {k} under mask"
        )
    convention = str(data["convention"]) if "convention" in data else "sportcenter_13"
    pose = pose.copy()
    pose[~mask, :3] = np.nan
    return pose, mask, convention


def write_gt(path: str | Path, pose: np.ndarray, mask: np.ndarray, convention: str) -> None:
    """Write xrmocap keypoints3d: pose (F,P,K,3|4) metres, mask (F,P,K); 4th channel 1.0 where valid.

    Masked-out joints are stored as NaN (never 0).
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.ndim != 4 or pose.shape[-1] not in (3, 4):
        raise ValueError(f"write_gt pose: expected shape (F,P,K,3), got {pose.shape}")
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != pose.shape[:3]:
        raise ValueError(f"write_gt mask: expected shape {pose.shape[:3]}, got {mask.shape}")
    xyz = pose[..., :3].copy()
    if np.any(mask & ~np.all(np.isfinite(xyz), axis=-1)):
        raise ValueError("write_gt pose: NaN/inf coordinates under a True mask")
    xyz[~mask] = np.nan
    out = np.concatenate([xyz, mask[..., None].astype(np.float64)], axis=-1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        np.savez_compressed(f, pose=out, mask=mask.astype(np.uint8), convention=np.array(convention))


# ---- scene folders ----------------------------------------------------------------------------
_FRAME_RE = re.compile(r"(\d+)$")


def frame_stamp_ns(frame: int, start_stamp_ns: int, fps: float) -> int:
    """Stamp (ns) of frame ``frame`` on a clock starting at ``start_stamp_ns`` with ``fps``."""
    return int(start_stamp_ns) + int(round(int(frame) * 1e9 / fps))


def frame_at_stamp(stamp_ns: int, start_stamp_ns: int, fps: float) -> int | None:
    """Nearest frame index within half a period of ``stamp_ns`` (ns), None before frame 0."""
    frame = int(round((int(stamp_ns) - int(start_stamp_ns)) * fps / 1e9))
    if frame < 0 or abs(frame_stamp_ns(frame, start_stamp_ns, fps) - int(stamp_ns)) > 0.5e9 / fps:
        return None
    return frame


def index_frame_files(folder: str | Path) -> dict[int, Path]:
    """frame index -> npz path in one view's folder: any ``*.npz`` whose stem ends in the frame
    number (``000012.npz``, ``frame_12.npz``); empty when the folder is absent."""
    folder = Path(folder)
    index: dict[int, Path] = {}
    if folder.is_dir():
        for p in sorted(folder.glob("*.npz")):
            m = _FRAME_RE.search(p.stem)
            if m:
                index.setdefault(int(m.group(1)), p)
    return index


class SceneFolder:
    """A scene folder on disk (layout in the module docstring); views = camera JSON stems."""

    def __init__(self, root: str | Path, rig: Rig | None = None):
        """``rig``: use this rig instead of cameras/ (e.g. a calibrated one; same camera
        names, and the intrinsics the detections were made with)."""
        self.root = Path(root)
        if not self.root.is_dir():
            raise ValueError(f"scene folder {str(self.root)!r}: no such folder")
        if rig is None and not (self.root / "cameras").is_dir():
            raise ValueError(f"scene folder {str(self.root)!r}: no cameras/ folder")
        self._rig: Rig | None = rig
        self._index: dict[str, dict[int, Path]] = {}
        info_path = self.root / "scene.json"
        self.info: dict = {}
        if info_path.is_file():
            try:
                self.info = json.loads(info_path.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ValueError(f"scene folder {str(info_path)!r}: unreadable JSON ({e})") from None

    # ---- writing --------------------------------------------------------------------------
    @classmethod
    def create(
        cls, root: str | Path, rig: Rig, info: Mapping | None = None, extrinsics: bool = True
    ) -> SceneFolder:
        """Make the folder, write cameras/ (``extrinsics`` False: intrinsics only, for
        calibration; such a scene's :attr:`rig` cannot be read, Rig.load_intrinsics reads it)
        and (when given) scene.json."""
        root = Path(root)
        root.mkdir(parents=True, exist_ok=True)
        rig.to_json_folder(root / "cameras", extrinsics=extrinsics)
        if info is not None:
            (root / "scene.json").write_text(json.dumps(dict(info), indent=2))
        return cls(root)

    def write_outputs(self, view: str, frame: int, outputs: Sequence[Mapping], float32: bool = True) -> Path:
        """Write dets/<view>/<frame:06d>.npz (float arrays as float32 by default, like the model)."""
        path = self.root / "dets" / view / f"{int(frame):06d}.npz"
        write_maem_npz(path, outputs, float32=float32)
        self._index.pop(view, None)
        return path

    def write_gt(self, pose: np.ndarray, mask: np.ndarray, convention: str = "sportcenter_13") -> None:
        write_gt(self.root / "gt.npz", pose, mask, convention)

    def write_image(self, view: str, frame: int, image: np.ndarray, quality: int = 90) -> Path:
        path = self.image_path(view, frame)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, quality]):
            raise ValueError(f"image {str(path)!r}: cv2.imwrite failed")
        return path

    # ---- reading --------------------------------------------------------------------------
    @property
    def rig(self) -> Rig:
        if self._rig is None:
            self._rig = Rig.from_json_folder(self.root / "cameras")
        return self._rig

    @property
    def views(self) -> list[str]:
        """Camera names in rig order (a view may still lack a dets/ folder)."""
        return self.rig.names

    @property
    def fps(self) -> float:
        return float(self.info.get("fps", DEFAULT_FPS))

    @property
    def start_stamp_ns(self) -> int:
        return int(self.info.get("start_stamp_ns", 0))

    @property
    def has_gt(self) -> bool:
        return (self.root / "gt.npz").is_file()

    def unknown_det_views(self) -> list[str]:
        """dets/ subfolders with no camera JSON (they cannot be used)."""
        dets = self.root / "dets"
        if not dets.is_dir():
            return []
        return sorted(p.name for p in dets.iterdir() if p.is_dir() and p.name not in self.rig)

    def frame_files(self, view: str) -> dict[int, Path]:
        """frame index -> npz path for one view (empty if dets/<view>/ is absent)."""
        if view not in self._index:
            self._index[view] = index_frame_files(self.root / "dets" / view)
        return self._index[view]

    @property
    def num_frames(self) -> int:
        """1 + the largest frame index of any view's detections (0 when there are none)."""
        last = [max(files) for v in self.views if (files := self.frame_files(v))]
        n = max(last) + 1 if last else 0
        return max(n, int(self.info.get("num_frames", 0)))

    def stamp_ns(self, frame: int) -> int:
        return frame_stamp_ns(frame, self.start_stamp_ns, self.fps)

    def frame_at(self, stamp_ns: int) -> int | None:
        """Nearest frame index within half a period of ``stamp_ns``, else None."""
        return frame_at_stamp(stamp_ns, self.start_stamp_ns, self.fps)

    def read_outputs(self, view: str, frame: int) -> list[dict]:
        if view not in self.rig:
            raise MissingDataError(f"scene {str(self.root)!r}: unknown view {view!r}; known: {self.views}")
        path = self.frame_files(view).get(int(frame))
        if path is None:
            if not (self.root / "dets" / view).is_dir():
                raise MissingDataError(f"scene {str(self.root)!r}: view {view!r} has no dets/{view}/ folder")
            raise MissingDataError(f"scene {str(self.root)!r}: no detections for view {view!r} frame {frame}")
        return read_maem_npz(path)

    def detections(self, view: str, frame: int) -> FrameDetections:
        """Rectified detections of one view and frame (MissingDataError / ValueError on bad files)."""
        outputs = self.read_outputs(view, frame)
        path = self.frame_files(view)[int(frame)]
        return outputs_to_detections(
            outputs, self.rig[view], self.stamp_ns(frame), where=f"npz {str(path)!r} outputs"
        )

    def capture_frame(self, view: str, frame: int) -> int | None:
        """The view's frame whose capture time (stamp + its camera's time_offset) is nearest
        ``frame``'s stamp, within half a period (None: no such frame); ``frame`` itself when the
        camera has no offset."""
        offset = self.rig[view].time_offset
        if not offset:
            return int(frame)
        files = sorted(self.frame_files(view))
        idx = match_capture_times(
            [self.stamp_ns(frame)], [self.stamp_ns(g) for g in files], offset, int(0.5e9 / self.fps)
        )[0]
        return files[idx] if idx >= 0 else None

    def detections_at(self, view: str, frame: int) -> FrameDetections:
        """The view's detections captured nearest the time of ``frame`` (:meth:`capture_frame`),
        stamped with their capture time: the offline pipeline's frame set member."""
        captured = self.capture_frame(view, frame)
        if captured is None:
            raise MissingDataError(
                f"scene {str(self.root)!r}: view {view!r} has no frame "
                f"captured near frame {frame} (time_offset "
                f"{self.rig[view].time_offset:+.4f} s)"
            )
        dets = self.detections(view, captured)
        dets.stamp_ns = capture_stamp_ns(dets.stamp_ns, self.rig[view].time_offset)
        return dets

    def gt(self) -> tuple[np.ndarray, np.ndarray, str]:
        return read_gt(self.root / "gt.npz")

    @property
    def has_det_ids(self) -> bool:
        return (self.root / DET_IDS).is_file()

    def write_det_ids(self, ids: Mapping[tuple[str, int], np.ndarray]) -> None:
        """det_ids.npz from {(view, frame): (N,) GT person per detection, -1 = false positive}."""
        arrays = {det_ids_key(v, f): np.asarray(a, dtype=np.int64) for (v, f), a in ids.items()}
        with open(self.root / DET_IDS, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub: **kwds

    def det_ids(self) -> dict[str, np.ndarray]:
        """{"<view>/<frame:06d>": (N,) int64} from det_ids.npz; ValueError naming a bad file."""
        path = self.root / DET_IDS
        if not path.is_file():
            raise MissingDataError(f"scene {str(self.root)!r}: no {DET_IDS} (written by maem-sim)")
        try:
            with np.load(path, allow_pickle=False) as z:
                out = {k: np.asarray(z[k]) for k in z.files}
        except (OSError, ValueError) as e:
            raise ValueError(f"{str(path)!r}: unreadable ({e})") from None
        for k, a in out.items():
            if a.ndim != 1 or a.dtype.kind not in "iu":
                raise ValueError(f"{str(path)!r}: {k}: expected (N,) integers, got {a.dtype} {a.shape}")
        return out

    def image_path(self, view: str, frame: int) -> Path:
        return self.root / "images" / view / f"{int(frame):06d}.jpg"
