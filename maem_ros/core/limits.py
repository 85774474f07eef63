"""Per-message bounds: work per frame stays bounded and absurd coordinates never become poses.

A well-formed message can still be hostile: 450 people in one clusters message blocked the
triangulation node for ~2 s (frames behind it overwritten in the DDS history), and pixel
coordinates of 1e30 were triangulated and published. The checks here reject such a message
with a :class:`LimitError` (reason ``too_many_detections`` / ``too_many_people`` /
``out_of_range``) before any per-person work, in O(size of the message) numpy reductions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.errors import InputError
from maem_ros.core.geometry.camera import Rig


class LimitError(InputError):
    """A message beyond the configured per-message bounds."""

    reason = "out_of_range"


@dataclass(frozen=True)
class InputLimits:
    """``max_detections`` per camera message, ``max_people`` clusters per frame, pixel
    coordinates within ``pixel_margin`` image sizes outside the image (px, rectified frame),
    world joints within ``world_extent_m`` of the world origin (m)."""

    max_detections: int = 100
    max_people: int = 50
    pixel_margin: float = 1.0
    world_extent_m: float = 200.0

    def __post_init__(self) -> None:
        for name in ("max_detections", "max_people"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if not self.pixel_margin >= 0:
            raise ValueError(f"pixel_margin: must be >= 0, got {self.pixel_margin}")
        if not self.world_extent_m > 0:
            raise ValueError(f"world_extent_m: must be > 0, got {self.world_extent_m}")


def _pixel_bounds(width: np.ndarray, height: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper (x, y) px bounds, shape (..., 2)."""
    size = np.stack([width, height], axis=-1).astype(np.float64)
    return -margin * size, (1.0 + margin) * size


def _first_outside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float | None:
    """The first coordinate of ``points`` (..., 2) outside [lo, hi] (NaN ignored), else None.

    Bounds broadcast per point (..., 2) or per axis (2,). A full-mesh detections message has
    ~440k coordinates; comparing them elementwise against the per-axis bounds is slow (numpy
    runs an inner loop of length 2), so per-axis bounds are first checked with NaN-ignoring
    min/max reductions over the whole array (vectorised, no temporary) and the elementwise
    pass runs only to name a value that is out of range."""
    if lo.shape == (2,) and hi.shape == (2,) and points.size:
        low, high = np.fmin.reduce(points, axis=None), np.fmax.reduce(points, axis=None)
        if not (low < lo.max() or high > hi.min()):  # NaN compares False: all missing
            return None
        low = [np.fmin.reduce(points[..., k], axis=None) for k in range(2)]
        high = [np.fmax.reduce(points[..., k], axis=None) for k in range(2)]
        if not any(low[k] < lo[k] or high[k] > hi[k] for k in range(2)):
            return None
    with np.errstate(invalid="ignore"):
        bad = (points < lo) | (points > hi)
    if not bad.any():
        return None
    return float(points[bad].flat[0])


def check_detections(dets: FrameDetections, rig: Rig, limits: InputLimits, where: str) -> None:
    """LimitError when ``dets`` has more than ``max_detections`` or a bbox, keypoint or vertex
    outside the camera's image by more than ``pixel_margin`` image sizes."""
    check_detection_arrays(dets.camera, dets.bboxes, dets.kpts2d, dets.verts2d, rig, limits, where)


def check_detection_arrays(
    camera: str,
    bboxes: np.ndarray,
    kpts2d: np.ndarray,
    vertices: np.ndarray | Callable[[bool], np.ndarray],
    rig: Rig,
    limits: InputLimits,
    where: str,
) -> None:
    """check_detections on one camera's arrays: bboxes (N, 4) px, kpts2d (N, J, 2) px and
    vertices (..., 2) px, or for a message whose vertices are not decoded yet a function of
    ``exact`` giving their extremes (2, 2) (rows min and max; exact=False: cheaper bounds that
    may be wider, wire.DetectionsMessage.vertex_extremes): the exact extremes are read only
    when the cheap bounds are not within the limits."""
    n = len(bboxes)
    if n > limits.max_detections:
        raise LimitError(
            f"{where}: {n} detections > max_detections {limits.max_detections}", "too_many_detections"
        )
    if n == 0:
        return
    cam = rig[camera]
    lo, hi = _pixel_bounds(np.array(cam.width), np.array(cam.height), limits.pixel_margin)
    if callable(vertices):
        extremes = vertices(False)
        vertices = extremes if _first_outside(extremes, lo, hi) is None else vertices(True)
    for name, pts in (("bbox", bboxes.reshape(n, -1, 2)), ("kpts2d", kpts2d), ("verts2d", vertices)):
        value = _first_outside(pts, lo, hi)
        if value is not None:
            raise LimitError(
                f"{where}: {name}: {value:g} px outside image {cam.width}x"
                f"{cam.height} by more than pixel_margin {limits.pixel_margin:g}"
            )


def check_clusters(
    num_clusters: int, camera: np.ndarray, kpts2d: np.ndarray, rig: Rig, limits: InputLimits, where: str
) -> None:
    """LimitError when a clusters message has more than ``max_people`` clusters or a member
    keypoint (``kpts2d`` (M,J,2) px of member camera index ``camera`` (M,)) outside its
    camera's image by more than ``pixel_margin`` image sizes."""
    if num_clusters > limits.max_people:
        raise LimitError(
            f"{where}: {num_clusters} people > max_people {limits.max_people}", "too_many_people"
        )
    if len(camera) == 0:
        return
    width = np.array([c.width for c in rig.cameras])[camera]
    height = np.array([c.height for c in rig.cameras])[camera]
    lo, hi = _pixel_bounds(width, height, limits.pixel_margin)
    value = _first_outside(kpts2d, lo[:, None], hi[:, None])
    if value is not None:
        raise LimitError(
            f"{where}: kpts2d: {value:g} px outside the member's image by more "
            f"than pixel_margin {limits.pixel_margin:g}"
        )


def mask_far_joints(joints: np.ndarray, limits: InputLimits) -> int:
    """Set joints (P,J,3 world m) farther than ``world_extent_m`` from the origin to NaN (a
    missing joint, in place); returns how many were masked."""
    with np.errstate(invalid="ignore"):
        far = np.abs(joints).max(axis=-1) > limits.world_extent_m
    joints[far] = np.nan
    return int(far.sum())
