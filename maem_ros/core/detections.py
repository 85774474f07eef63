"""Per-camera, per-frame person detections as the frontend delivers them.

All 2D coordinates are in the RECTIFIED pinhole image of the camera (px);
3D keypoints are in metres in the detection's own camera-relative frame (the
association only compares them up to a similarity transform).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np


@dataclass
class FrameDetections:
    """N detections of one camera at one stamp (J keypoints, V mesh vertices each).

    bboxes (N,4) x1 y1 x2 y2 px; scores (N,); kpts2d (N,J,2) px; kpts3d (N,J,3) m;
    verts2d (N,V,2) px, float32 (V may be 0 when no mesh is available).
    ``stamp_ns`` is the image capture time in integer nanoseconds.
    """

    camera: str
    stamp_ns: int
    bboxes: np.ndarray
    scores: np.ndarray
    kpts2d: np.ndarray
    kpts3d: np.ndarray
    verts2d: np.ndarray

    def __post_init__(self) -> None:
        self.bboxes = np.asarray(self.bboxes, dtype=np.float64)
        self.scores = np.asarray(self.scores, dtype=np.float64)
        self.kpts2d = np.asarray(self.kpts2d, dtype=np.float64)
        self.kpts3d = np.asarray(self.kpts3d, dtype=np.float64)
        self.verts2d = np.asarray(self.verts2d, dtype=np.float32)
        self.stamp_ns = int(self.stamp_ns)

    @property
    def n(self) -> int:
        return int(self.bboxes.shape[0]) if self.bboxes.ndim == 2 else 0

    @property
    def num_joints(self) -> int:
        return int(self.kpts2d.shape[1]) if self.kpts2d.ndim == 3 else 0

    @property
    def num_vertices(self) -> int:
        return int(self.verts2d.shape[1]) if self.verts2d.ndim == 3 else 0

    @property
    def centers(self) -> np.ndarray:
        """(N,2) bbox centres, rectified px."""
        return 0.5 * (self.bboxes[:, :2] + self.bboxes[:, 2:])

    @classmethod
    def empty(cls, camera: str, stamp_ns: int, num_joints: int, num_vertices: int) -> "FrameDetections":
        return cls(camera, stamp_ns, np.zeros((0, 4)), np.zeros(0), np.zeros((0, num_joints, 2)),
                   np.zeros((0, num_joints, 3)), np.zeros((0, num_vertices, 2), np.float32))

    def select(self, index: np.ndarray) -> "FrameDetections":
        """Subset by boolean mask or integer index (copies)."""
        return FrameDetections(self.camera, self.stamp_ns, self.bboxes[index], self.scores[index],
                               self.kpts2d[index], self.kpts3d[index], self.verts2d[index])

    def validate(self, known_cameras: Iterable[str] | None = None) -> "FrameDetections":
        """Raise ValueError naming the first bad field; return self when valid."""
        where = f"detections of camera {self.camera!r}"
        if known_cameras is not None and self.camera not in set(known_cameras):
            raise ValueError(f"{where}: camera: unknown camera {self.camera!r}")
        if self.bboxes.ndim != 2 or self.bboxes.shape[1] != 4:
            raise ValueError(f"{where}: bbox: expected shape (N,4), got {self.bboxes.shape}")
        n = self.bboxes.shape[0]
        _check_shape(where, "score", self.scores, (n,))
        if self.kpts2d.ndim != 3 or self.kpts2d.shape[0] != n or self.kpts2d.shape[2] != 2:
            raise ValueError(f"{where}: kpts2d: expected shape ({n},J,2), got {self.kpts2d.shape}")
        j = self.kpts2d.shape[1]
        _check_shape(where, "kpts3d", self.kpts3d, (n, j, 3))
        if self.verts2d.ndim != 3 or self.verts2d.shape[0] != n or self.verts2d.shape[2] != 2:
            raise ValueError(f"{where}: verts2d: expected shape ({n},V,2), got {self.verts2d.shape}")
        for field, arr in (("bbox", self.bboxes), ("score", self.scores), ("kpts2d", self.kpts2d),
                           ("kpts3d", self.kpts3d), ("verts2d", self.verts2d)):
            bad = ~np.isfinite(arr)
            if bad.any():
                det = int(np.argwhere(bad)[0][0]) if arr.ndim > 1 else int(np.argmax(bad))
                raise ValueError(f"{where}: {field}: NaN or inf in detection {det}")
        inverted = (self.bboxes[:, 2] < self.bboxes[:, 0]) | (self.bboxes[:, 3] < self.bboxes[:, 1])
        if inverted.any():
            raise ValueError(f"{where}: bbox: inverted box (x2<x1 or y2<y1) in detection "
                             f"{int(np.argmax(inverted))}")
        if np.any((self.scores < 0) | (self.scores > 1)):
            raise ValueError(f"{where}: score: outside [0, 1] in detection "
                             f"{int(np.argmax((self.scores < 0) | (self.scores > 1)))}")
        return self


def _check_shape(where: str, field: str, arr: np.ndarray, shape: tuple[int, ...]) -> None:
    if arr.shape != shape:
        raise ValueError(f"{where}: {field}: expected shape {shape}, got {arr.shape}")
