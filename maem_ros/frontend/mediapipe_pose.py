"""mediapipe backend: multi-person BlazePose (MediaPipe Pose, CPU) per rectified image.

The PyPI ``mediapipe`` wheel ships the BlazePose detector and the "full" landmark model
(mediapipe/modules/pose_detection/pose_detection.tflite, pose_landmark/pose_landmark_full.tflite),
so this backend runs offline on a CPU with nothing to download. The legacy solutions API it
uses (``mp.solutions.pose.Pose``) finds ONE person per call (the Tasks API's ``num_poses`` needs
.task model bundles the wheel does not ship), so people are found by masking: run, grey out the
found person's segmentation mask (dilated) and run again, up to ``max_people`` passes or until no
person is found. Per person:

* kpts2d: the 33 image landmarks (rectified px; the node passes the rectified image); a landmark
  whose visibility is under ``min_visibility`` is NaN (not seen: BlazePose places occluded
  landmarks anyway, and such guesses are what disagrees most between views);
* kpts3d: the 33 ``pose_world_landmarks`` (all of them: the association compares whole bodies)
  (metres, hip-centred, model axes) moved into the camera frame (OpenCV axes, metres) by the pose
  that best projects them onto the image landmarks (cv2.solvePnP, SQPnP, on the landmarks with
  visibility >= ``pnp_min_visibility``);
* score: mean landmark visibility over the body joints (shoulders, elbows, wrists, hips, knees,
  ankles): MediaPipe gives no detection score, visibility says how much of the body it saw;
* bbox: the segmentation mask's bounding box (x1 y1 x2 y2 rectified px);
* no mesh vertices (V = 0): run the association with ``epipolar_gate: sparse``.

Detections are dropped (counted in ``stats``) when the pass found the same person again (its
landmarks fall mostly inside an earlier person's mask), when the body is too small
(``min_bbox_height``), or when the pose cannot be placed in the camera (PnP fails).

Install (optional extra; the wheel pins numpy<2 and opencv-contrib-python, which would downgrade
this project's numpy and fight opencv-python-headless over the cv2 package, while the solutions
API runs fine on both)::

    pip install '.[mediapipe]'                   # its runtime deps: absl-py, attrs, flatbuffers, protobuf<5
    pip install --no-deps mediapipe==0.10.21     # the wheel itself (models included)

or ``make mediapipe``.

Options (frontend parameters; unknown keys are ignored):
  max_people             passes per image (default 4)
  min_detection_confidence  BlazePose detector threshold (default 0.5)
  min_bbox_height        px, smaller people are dropped (default 0 = keep all)
  mask_threshold         segmentation probability counted as the person (default 0.5)
  mask_dilate            px grown around the mask before greying it out (default 15)
  duplicate_overlap      fraction of a new person's landmarks inside earlier masks that makes it
                         a duplicate (default 0.6)
  pnp_min_visibility     landmarks used to place the 3D pose (default 0.5)
  min_visibility         landmarks under this visibility are published as NaN (default 0 = all)
  keypoint_convention    blazepose_33 | sportcenter_13 | coco_17 (default blazepose_33)
  pose_factory           callable(options) -> object with ``process(rgb)`` like mp Pose (tests)
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.skeleton import BLAZEPOSE_33, KeypointConvention, convert, get_convention

from .base import Estimator, check_bgr_image, option_float, option_int

MEDIAPIPE_VERSION = "0.10.21"
INSTALL_HELP = (
    "the mediapipe backend needs the mediapipe wheel: pip install '.[mediapipe]' && "
    f"pip install --no-deps mediapipe=={MEDIAPIPE_VERSION} (or make mediapipe); --no-deps "
    "because the wheel pins numpy<2 and opencv-contrib-python, which would replace this "
    "project's numpy and opencv-python-headless"
)
#: the grey a found person is painted with before the next pass
_MASK_GREY = 128
#: body joints whose visibility makes the score (BlazePose indices 11-16, 23-28)
_SCORE_JOINTS = np.array([11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28])


def import_mediapipe():
    """The mediapipe module, or ImportError with the install command."""
    try:
        import mediapipe as mp

        _ = mp.solutions.pose.Pose
    except (ImportError, AttributeError) as e:
        raise ImportError(f"{INSTALL_HELP} ({type(e).__name__}: {e})") from None
    return mp


def official_pose(options: Mapping[str, Any]):
    """mp.solutions.pose.Pose in static-image mode with segmentation (the shipped full model)."""
    mp = import_mediapipe()
    return mp.solutions.pose.Pose(
        static_image_mode=True,
        model_complexity=1,
        enable_segmentation=True,
        min_detection_confidence=option_float(options, "min_detection_confidence", 0.5),
    )


def landmarks_array(landmarks, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe NormalizedLandmarkList -> ((33,2) px, (33,) visibility)."""
    a = np.array([(p.x, p.y, p.visibility) for p in landmarks.landmark], dtype=np.float64)
    return a[:, :2] * (width, height), a[:, 2]


def world_array(landmarks) -> np.ndarray:
    """MediaPipe LandmarkList (pose_world_landmarks) -> (33,3) metres."""
    return np.array([(p.x, p.y, p.z) for p in landmarks.landmark], dtype=np.float64)


def place_in_camera(world: np.ndarray, uv: np.ndarray, use: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """(J,3) model-frame metres -> (J,3) camera-frame metres via the PnP pose that projects the
    ``use`` joints onto ``uv`` (rectified px, intrinsics K); None when PnP fails."""
    if int(use.sum()) < 4:
        return None
    ok, rvec, tvec = cv2.solvePnP(
        world[use].astype(np.float64), uv[use].astype(np.float64), K, None, flags=cv2.SOLVEPNP_SQPNP
    )
    if not ok:
        return None
    R = cv2.Rodrigues(rvec)[0]
    X = world @ R.T + tvec.reshape(1, 3)
    if not np.all(np.isfinite(X)) or np.median(X[:, 2]) <= 0:
        return None
    return X


class MediapipeEstimator(Estimator):
    """Multi-person BlazePose on each rectified image of a camera -> FrameDetections (V = 0)."""

    needs_image = True

    def __init__(self, options: Mapping[str, Any], rig: Rig):
        options = dict(options or {})
        self.rig = rig
        self.max_people = option_int(options, "max_people", 4, minimum=1)
        self.min_bbox_height = option_float(options, "min_bbox_height", 0.0)
        self.mask_threshold = option_float(options, "mask_threshold", 0.5)
        self.mask_dilate = option_int(options, "mask_dilate", 15, minimum=0)
        self.duplicate_overlap = option_float(options, "duplicate_overlap", 0.6)
        self.pnp_min_visibility = option_float(options, "pnp_min_visibility", 0.5)
        self.min_visibility = option_float(options, "min_visibility", 0.0)
        for key in (
            "mask_threshold",
            "duplicate_overlap",
            "pnp_min_visibility",
            "min_detection_confidence",
            "min_visibility",
        ):
            value = option_float(options, key, 0.5)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"frontend option {key!r}: must be in [0, 1], got {value}")
        if self.min_bbox_height < 0:
            raise ValueError(
                f"frontend option 'min_bbox_height': must be >= 0 px, got {self.min_bbox_height}"
            )
        self.convention: KeypointConvention = get_convention(
            str(options.get("keypoint_convention", BLAZEPOSE_33.name) or BLAZEPOSE_33.name)
        )
        # fails here (with the message) rather than at the first image
        convert(np.zeros((BLAZEPOSE_33.num_joints, 2)), self.convention, BLAZEPOSE_33.name)
        factory = options.get("pose_factory")
        if factory is not None and not callable(factory):
            raise ValueError("frontend option 'pose_factory': expected a callable")
        self.pose = factory(options) if factory is not None else official_pose(options)
        kernel = 2 * self.mask_dilate + 1
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel, kernel))
        #: counters: frames, passes (model calls), detections, dropped_duplicate, dropped_small,
        #: dropped_pnp
        self.stats: dict[str, int] = dict(
            frames=0, passes=0, detections=0, dropped_duplicate=0, dropped_small=0, dropped_pnp=0
        )

    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None) -> FrameDetections:
        """Rectified BGR uint8 (H,W,3) image -> detections (rectified px, camera metres)."""
        image = check_bgr_image(image, "mediapipe", camera.name)
        self.stats["frames"] += 1
        h, w = image.shape[:2]
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        taken = np.zeros((h, w), dtype=bool)
        people: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []
        for _ in range(self.max_people):
            self.stats["passes"] += 1
            result = self.pose.process(rgb)
            if result.pose_landmarks is None:
                break
            uv, vis = landmarks_array(result.pose_landmarks, w, h)
            mask = self._person_mask(result, uv, h, w)
            person = self._person(camera, uv, vis, result, mask, taken)
            if person is not None:
                people.append(person)
            grown = cv2.dilate(mask.astype(np.uint8), self._kernel) > 0
            if not grown.any():
                break  # nothing to grey out: the next pass would find the same person
            taken |= grown
            rgb[grown] = _MASK_GREY  # our own converted copy: the next pass sees it greyed
        self.stats["detections"] += len(people)
        return self._detections(camera, stamp_ns, people)

    # ---- helpers ----------------------------------------------------------------------------
    def _person_mask(self, result, uv: np.ndarray, h: int, w: int) -> np.ndarray:
        """(H,W) bool: the segmentation mask, else the landmarks' convex hull (no mask output)."""
        seg = getattr(result, "segmentation_mask", None)
        if seg is not None and np.shape(seg) == (h, w):
            return np.asarray(seg) > self.mask_threshold
        mask = np.zeros((h, w), np.uint8)
        hull = cv2.convexHull(np.round(uv).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
        return mask > 0

    def _person(
        self, camera: Camera, uv: np.ndarray, vis: np.ndarray, result, mask: np.ndarray, taken: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """(bbox, kpts2d, kpts3d, score) of one pass's person, None when dropped (counted)."""
        h, w = mask.shape
        px = np.round(uv).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        if taken.any() and inside.any():
            overlap = taken[px[inside, 1], px[inside, 0]].mean()
            if overlap >= self.duplicate_overlap:
                self.stats["dropped_duplicate"] += 1
                return None
        ys, xs = np.nonzero(mask)
        if len(xs):
            bbox = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)
        else:
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            bbox = np.array([lo[0], lo[1], hi[0], hi[1]])
        if bbox[3] - bbox[1] < self.min_bbox_height:
            self.stats["dropped_small"] += 1
            return None
        world = result.pose_world_landmarks
        X = (
            None
            if world is None
            else place_in_camera(world_array(world), uv, vis >= self.pnp_min_visibility, camera.K_rect)
        )
        if X is None:
            self.stats["dropped_pnp"] += 1
            return None
        seen = np.where((vis >= self.min_visibility)[:, None], uv, np.nan)
        return bbox, seen, X, float(np.clip(vis[_SCORE_JOINTS].mean(), 0.0, 1.0))

    def _detections(self, camera: Camera, stamp_ns: int, people) -> FrameDetections:
        conv = self.convention
        if not people:
            return FrameDetections.empty(camera.name, stamp_ns, conv.num_joints, 0)
        bboxes, kp2d, kp3d = (np.stack([p[i] for p in people]) for i in range(3))
        scores = np.array([p[3] for p in people])
        return FrameDetections(
            camera.name,
            stamp_ns,
            bboxes,
            scores,
            convert(kp2d, conv, BLAZEPOSE_33.name),
            convert(kp3d, conv, BLAZEPOSE_33.name),
            np.zeros((len(people), 0, 2), np.float32),
        )
