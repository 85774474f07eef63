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


def distort_normalised(camera: Camera, xn: np.ndarray) -> np.ndarray:
    """(...,2) normalised pinhole coordinates -> (...,2) raw px.

    Same lens models as ``Camera.project`` (OpenCV plumb_bob / rational_polynomial, fisheye
    equidistant), in plain numpy: about 10x faster than cv2.projectPoints on mesh-sized arrays.
    """
    x, y = xn[..., 0], xn[..., 1]
    D = camera.D
    if camera.is_fisheye:
        r = np.hypot(x, y)
        th = np.arctan(r)
        th2 = th * th
        thd = th * (1 + th2 * (D[0] + th2 * (D[1] + th2 * (D[2] + th2 * D[3]))))
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(r > 1e-12, thd / r, 1.0)
        xd, yd = x * f, y * f
    else:
        k = np.zeros(8)
        k[:len(D)] = D
        k1, k2, p1, p2, k3, k4, k5, k6 = k
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    K = camera.K
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def distort_points(camera: Camera, uv_rect: np.ndarray) -> np.ndarray:
    """(...,2) rectified px -> (...,2) raw px (numpy twin of ``Camera.distort_points``)."""
    Ki = np.linalg.inv(camera.K_rect[:2, :2])
    return distort_normalised(camera, (np.asarray(uv_rect, float) - camera.K_rect[:2, 2]) @ Ki.T)


def normalised(camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(...,3) world m -> normalised coordinates (...,2) and a mask (...,) of points in front of
    the camera and inside 95 % of the lens fold radius."""
    Xc = camera.world_to_camera(X)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = Xc[..., :2] / z[..., None]
    ok = (z > 1e-6) & (np.linalg.norm(xn, axis=-1) < 0.95 * fold_radius(camera))
    return xn, ok


def project_raw(camera: Camera, X: np.ndarray) -> np.ndarray:
    """(...,3) world m -> (...,2) raw px; NaN behind the camera or beyond the lens fold."""
    xn, ok = normalised(camera, X)
    with np.errstate(invalid="ignore"):
        uv = distort_normalised(camera, np.where(ok[..., None], xn, 0.0))
    return np.where(ok[..., None], uv, np.nan)


def inside_image(camera: Camera, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: finite px inside [margin, size - 1 - margin]."""
    with np.errstate(invalid="ignore"):
        return ((uv[..., 0] >= margin) & (uv[..., 0] <= camera.width - 1 - margin)
                & (uv[..., 1] >= margin) & (uv[..., 1] <= camera.height - 1 - margin))
