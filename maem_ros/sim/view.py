"""Safe projection into a strongly distorted raw image.

Polynomial lens models fold back beyond some normalised radius: a point far outside the field
of view would land inside the image. The simulator treats every point beyond 95 % of the fold
radius as outside the image.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from maem_ros.core.geometry.camera import Camera


def fold_radius(camera: Camera) -> float:
    """Normalised radius (tan of the off-axis angle) where the raw radius stops growing; inf if never."""
    return _fold_radius(
        camera.distortion_model, tuple(float(x) for x in camera.D), tuple(float(x) for x in camera.K.ravel())
    )


@lru_cache(maxsize=64)
def _fold_radius(model: str, D: tuple, K: tuple) -> float:
    cam = Camera("fold", np.reshape(K, (3, 3)), np.eye(3), np.zeros(3), 100, 100, model, np.asarray(D, float))
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
    return np.stack(distort_xy(camera, xn[..., 0], xn[..., 1]), axis=-1)


def distort_xy(camera: Camera, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates x, y (...) -> raw px u, v (...), as ``distort_normalised``.

    Works on separate (contiguous) coordinate arrays, in place on few temporaries, with the same
    operation order as the textbook formula (bit-identical results).
    """
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
        xd, yd = _plumb_bob(D, x, y)
    K = camera.K
    u = K[0, 0] * xd
    if K[0, 1] != 0:
        u += K[0, 1] * yd
    u += K[0, 2]
    yd *= K[1, 1]
    yd += K[1, 2]
    return u, yd


def _plumb_bob(D: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV radial-tangential (rational) distortion of normalised (x, y): (xd, yd), unitless.

    xd = x radial + 2 p1 x y + p2 (r2 + 2 x x), yd = y radial + p1 (r2 + 2 y y) + 2 p2 x y,
    radial = (1 + r2 (k1 + r2 (k2 + r2 k3))) / (1 + r2 (k4 + r2 (k5 + r2 k6))); the denominator is
    skipped when k4 = k5 = k6 = 0 (it is then exactly 1).
    """
    k = np.zeros(8)
    k[: len(D)] = D
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    xx = x * x
    r2 = y * y
    r2 += xx
    radial = r2 * k3  # Horner, in place
    radial += k2
    radial *= r2
    radial += k1
    radial *= r2
    radial += 1
    if k4 or k5 or k6:
        radial /= 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    xd = x * radial
    t = np.multiply(x, 2 * p1)  # 2 p1 x y
    t *= y
    xd += t
    xx *= 2  # 2 x x (exact)
    xx += r2
    xx *= p2
    xd += xx
    yd = np.multiply(y, radial, out=radial)
    yy = np.multiply(y, 2, out=xx)  # 2 y y
    yy *= y
    yy += r2
    yy *= p1
    yd += yy
    np.multiply(x, 2 * p2, out=t)  # 2 p2 x y
    t *= y
    yd += t
    return xd, yd


def distort_points(camera: Camera, uv_rect: np.ndarray) -> np.ndarray:
    """(...,2) rectified px -> (...,2) raw px (numpy twin of ``Camera.distort_points``)."""
    Ki = np.linalg.inv(camera.K_rect[:2, :2])
    return distort_normalised(camera, (np.asarray(uv_rect, float) - camera.K_rect[:2, 2]) @ Ki.T)


def world_to_camera(camera: Camera, X: np.ndarray) -> np.ndarray:
    """(...,3) world m -> (...,3) camera-frame m (as ``Camera.world_to_camera``, one temporary)."""
    Xc = np.asarray(X, dtype=np.float64) @ camera.R.T
    Xc += camera.t
    return Xc


def camera_to_normalised_xy(camera: Camera, Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(...,3) camera-frame m -> normalised coordinates x, y (...) and a mask (...) of points in
    front of the camera and inside 95 % of the lens fold radius."""
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = Xc[..., 0] / z, Xc[..., 1] / z
        ok = z > 1e-6
        fold = 0.95 * fold_radius(camera)
        if np.isfinite(fold):
            r = x * x
            r += y * y
            ok &= np.sqrt(r, out=r) < fold  # |xn| as np.linalg.norm computes it
        else:
            ok &= np.isfinite(x) & np.isfinite(y)  # |xn| < inf
    return x, y, ok


def normalised(camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(...,3) world m -> normalised coordinates (...,2) and a mask (...,) of points in front of
    the camera and inside 95 % of the lens fold radius."""
    x, y, ok = camera_to_normalised_xy(camera, world_to_camera(camera, X))
    return np.stack([x, y], axis=-1), ok


def normalised_to_raw_xy(
    camera: Camera, x: np.ndarray, y: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised x, y (...) and their mask from ``camera_to_normalised_xy`` -> raw px u, v (...),
    NaN where the mask is False."""
    if not ok.all():
        x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
    with np.errstate(invalid="ignore"):
        u, v = distort_xy(camera, x, y)
    u[~ok] = np.nan
    v[~ok] = np.nan
    return u, v


def project_raw_xy(camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(...,3) world m -> raw px u, v (...); NaN behind the camera or beyond the lens fold."""
    return normalised_to_raw_xy(camera, *camera_to_normalised_xy(camera, world_to_camera(camera, X)))


def project_raw(camera: Camera, X: np.ndarray) -> np.ndarray:
    """(...,3) world m -> (...,2) raw px; NaN behind the camera or beyond the lens fold."""
    return np.stack(project_raw_xy(camera, X), axis=-1)


def camera_to_rectified_xy(camera: Camera, Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(...,3) camera-frame m -> rectified pinhole px u, v (...); NaN behind the camera
    (bit-identical to ``Camera.project_rectified`` after ``world_to_camera``)."""
    K = camera.K_rect
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        if K[0, 1] != 0 or K[1, 0] != 0:  # skewed: the general 2x2 product
            uv = (Xc[..., :2] / z[..., None]) @ K[:2, :2].T
            u, v = uv[..., 0] + K[0, 2], uv[..., 1] + K[1, 2]
        else:
            u, v = Xc[..., 0] / z, Xc[..., 1] / z
            u *= K[0, 0]
            u += K[0, 2]
            v *= K[1, 1]
            v += K[1, 2]
    behind = z <= 0
    u[behind] = np.nan
    v[behind] = np.nan
    return u, v


def camera_to_rectified(camera: Camera, Xc: np.ndarray) -> np.ndarray:
    """(...,3) camera-frame m -> (...,2) rectified pinhole px; NaN behind the camera."""
    return np.stack(camera_to_rectified_xy(camera, Xc), axis=-1)


def inside_image(camera: Camera, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: finite px inside [margin, size - 1 - margin]."""
    return inside_image_xy(camera, uv[..., 0], uv[..., 1], margin)


def inside_image_xy(camera: Camera, u: np.ndarray, v: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: finite px u, v inside [margin, size - 1 - margin]."""
    with np.errstate(invalid="ignore"):
        return (
            (u >= margin)
            & (u <= camera.width - 1 - margin)
            & (v >= margin)
            & (v <= camera.height - 1 - margin)
        )
