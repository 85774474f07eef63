"""Rectifier: a dot drawn in the raw image lands where the camera model puts it."""
from __future__ import annotations

import numpy as np
import pytest

from helpers_scene import sportcenter_camera

from maem_ros.core.geometry.camera import Camera
from maem_ros.frontend.rectify import Rectifier


def _fisheye_camera() -> Camera:
    K = [[420.0, 0, 641.5], [0, 421.0, 398.2], [0, 0, 1]]
    return Camera("fish", K, np.eye(3), [0, 0, 10], 1280, 800, "equidistant",
                  [0.08, -0.02, 0.004, -0.0005])


def _rational_camera_with_k_rect() -> Camera:
    K = [[900.0, 0, 480.0], [0, 905.0, 300.0], [0, 0, 1]]
    K_rect = [[700.0, 0, 470.0], [0, 700.0, 310.0], [0, 0, 1]]
    return Camera("rat", K, np.eye(3), [0, 0, 10], 960, 600, "rational_polynomial",
                  [-0.2, 0.05, 0.001, -0.001, 0.0, 0.01, 0.002, 0.0], K_rect=K_rect)


def _grid(cam: Camera, n: int = 5, margin: float = 0.12) -> np.ndarray:
    xs = np.linspace(margin * cam.width, (1 - margin) * cam.width, n)
    ys = np.linspace(margin * cam.height, (1 - margin) * cam.height, n)
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def _draw_blobs(shape: tuple[int, int], centres: np.ndarray, sigma: float = 1.2) -> np.ndarray:
    h, w = shape
    img = np.zeros((h, w), np.float64)
    yy, xx = np.mgrid[0:h, 0:w]
    for u, v in centres:
        x0, x1 = int(max(u - 8, 0)), int(min(u + 9, w))
        y0, y1 = int(max(v - 8, 0)), int(min(v + 9, h))
        img[y0:y1, x0:x1] += np.exp(-((xx[y0:y1, x0:x1] - u) ** 2 + (yy[y0:y1, x0:x1] - v) ** 2)
                                    / (2 * sigma ** 2))
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)


def _centroid(img: np.ndarray, u: float, v: float, r: int = 10) -> np.ndarray:
    x0, y0 = int(round(u)) - r, int(round(v)) - r
    patch = img[y0:y0 + 2 * r + 1, x0:x0 + 2 * r + 1].astype(np.float64)
    assert patch.sum() > 0, f"no blob near ({u:.1f}, {v:.1f})"
    yy, xx = np.mgrid[y0:y0 + patch.shape[0], x0:x0 + patch.shape[1]]
    return np.array([(patch * xx).sum(), (patch * yy).sum()]) / patch.sum()


@pytest.mark.parametrize("make_camera", [sportcenter_camera, _fisheye_camera,
                                         _rational_camera_with_k_rect])
def test_dot_lands_at_rectified_position(make_camera):
    cam = make_camera()
    p_rect = _grid(cam)
    p_raw = cam.distort_points(p_rect)
    inside = np.all((p_raw > 12) & (p_raw < [cam.width - 12, cam.height - 12]), axis=1)
    assert inside.sum() >= 15
    p_rect, p_raw = p_rect[inside], p_raw[inside]
    # the distortion is strong enough for the test to mean something
    assert np.max(np.linalg.norm(p_raw - p_rect, axis=1)) > 15.0
    raw = _draw_blobs((cam.height, cam.width), p_raw)
    rect = Rectifier(cam).rectify(np.dstack([raw, raw // 2, raw]))
    assert rect.shape == (cam.height, cam.width, 3) and rect.dtype == np.uint8
    found = np.array([_centroid(rect[..., 0], u, v) for u, v in p_rect])
    err = np.linalg.norm(found - p_rect, axis=1)
    assert err.max() < 0.25, f"max error {err.max():.3f} px"
    # without rectification the dots are clearly elsewhere (the test can fail)
    assert np.max(np.linalg.norm(p_raw - p_rect, axis=1)) > 10 * err.max()


def test_mono_image_and_maps_built_once():
    cam = _fisheye_camera()
    r = Rectifier(cam)
    img = np.full((cam.height, cam.width), 200, np.uint8)
    out = r(img)
    assert out.shape == img.shape
    m1 = r.maps()[0]
    r(img)
    assert r.maps()[0] is m1
    # the image centre stays filled, corners of a barrel-undistorted image may be black
    assert out[cam.height // 2, cam.width // 2] == 200


def test_identity_camera_passes_image_through():
    cam = Camera("pin", [[500, 0, 320], [0, 500, 240], [0, 0, 1]], np.eye(3), [0, 0, 1], 640, 480)
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    assert Rectifier(cam).rectify(img) is img


def test_wrong_size_is_a_clear_error():
    cam = _fisheye_camera()
    with pytest.raises(ValueError, match=r"image is 640x400 but the rig calibration is 1280x800"):
        Rectifier(cam).rectify(np.zeros((400, 640, 3), np.uint8))
    with pytest.raises(ValueError, match="expected an image array"):
        Rectifier(cam).rectify(None)


def test_identity_rectification_accepts_any_image_size():
    """No distortion and K_rect == K: nothing to remap, so a calibration without a stored
    size (guessed from the principal point) does not reject the real frames."""
    cam = Camera("h", [[1200, 0, 1022], [0, 1200, 779.5], [0, 0, 1]], np.eye(3), [0, 0, 30],
                 2044, 1559)
    img = np.zeros((1536, 2048, 3), np.uint8)
    assert Rectifier(cam).rectify(img) is img
    with pytest.raises(ValueError, match="expected an image array"):
        Rectifier(cam).rectify(np.zeros((0, 0), np.uint8))
