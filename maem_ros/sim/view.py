"""Safe projection into a strongly distorted raw image.

Polynomial lens models fold back beyond some normalised radius: a point far outside the field
of view would land inside the image. The simulator treats every point beyond 95 % of the fold
radius as outside the image.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..core.camera import Camera


def fold_radius(camera: Camera) -> float:
    """Normalised radius (tan of the off-axis angle) where the raw radius stops growing; inf if never."""
    return _fold_radius(camera.distortion_model, tuple(float(x) for x in camera.D),
                        tuple(float(x) for x in camera.K.ravel()))


@lru_cache(maxsize=64)
def _fold_radius(model: str, D: tuple, K: tuple) -> float:
    cam = Camera("fold", np.reshape(K, (3, 3)), np.eye(3), np.zeros(3), 100, 100, model, list(D))
    if not cam.has_distortion:
        return float("inf")
    r = np.linspace(0.0, 6.0, 1201)[1:]
    ang = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    xn = (r[None, :, None] * np.stack([np.cos(ang), np.sin(ang)], 1)[:, None, :]).reshape(-1, 2)
    uv = cam._distort_normalised(xn).reshape(len(ang), len(r), 2)
    rd = np.linalg.norm(uv - cam.K[:2, 2], axis=2)
    falling = np.diff(rd, axis=1) <= 0
    first = np.where(falling.any(axis=1), falling.argmax(axis=1), len(r) - 1)
    return float(r[first.min()]) if falling.any() else float("inf")


def project_raw(camera: Camera, X: np.ndarray) -> np.ndarray:
    """(...,3) world m -> (...,2) raw px; NaN behind the camera or beyond the lens fold."""
    Xc = camera.world_to_camera(X)
    with np.errstate(divide="ignore", invalid="ignore"):
        rn = np.linalg.norm(Xc[..., :2], axis=-1) / Xc[..., 2]
    ok = (Xc[..., 2] > 1e-6) & (rn < 0.95 * fold_radius(camera))
    uv = camera.project(np.where(ok[..., None], X, np.nan))
    return np.where(ok[..., None], uv, np.nan)


def inside_image(camera: Camera, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: finite px inside [margin, size - 1 - margin]."""
    with np.errstate(invalid="ignore"):
        return ((uv[..., 0] >= margin) & (uv[..., 0] <= camera.width - 1 - margin)
                & (uv[..., 1] >= margin) & (uv[..., 1] <= camera.height - 1 - margin))
