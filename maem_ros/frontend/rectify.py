"""Undistort raw camera images into the rectified pinhole image of the rig (doc/design.md §4).

Every 2D coordinate the frontend publishes is in the rectified image with
intrinsics ``camera.K_rect`` and the calibration's image size, so the image is
remapped once per frame here and stages 2 and 3 never undistort again.
"""

from __future__ import annotations

import cv2
import numpy as np

from maem_ros.core.geometry.camera import Camera


class Rectifier:
    """Raw (distorted) BGR/mono image -> rectified pinhole image (K_rect, calibration size).

    The remap tables are computed lazily on the first frame and kept: the image
    size is fixed by the calibration, so they are built once per camera. A frame
    whose size differs from the calibration raises ValueError: scaling K to
    another resolution would silently put every published coordinate in a
    different pixel grid than the rig's K_rect, so the camera must be recalibrated
    (or the rig entry rescaled) instead.
    """

    def __init__(self, camera: Camera, interpolation: int = cv2.INTER_LINEAR):
        self.camera = camera
        self.interpolation = interpolation
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) px of both the raw and the rectified image."""
        return self.camera.width, self.camera.height

    @property
    def is_identity(self) -> bool:
        """True when the raw image already is the rectified one (no distortion, K == K_rect)."""
        cam = self.camera
        return not cam.has_distortion and np.array_equal(cam.K, cam.K_rect)

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The (map1, map2) remap tables (fixed-point CV_16SC2), built on first use."""
        if self._maps is None:
            self._maps = build_maps(self.camera)
        return self._maps

    def check_image(self, image: np.ndarray) -> None:
        """Raise ValueError unless ``image`` is a non-empty (H,W[,C]) array."""
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
            raise ValueError(
                f"camera {self.camera.name!r}: expected an image array (H,W[,C]), "
                f"got {type(image).__name__} {getattr(image, 'shape', '')}"
            )

    def check_size(self, image: np.ndarray) -> None:
        """Raise ValueError unless ``image`` has the calibration's size."""
        self.check_image(image)
        h, w = image.shape[:2]
        if (w, h) != self.size:
            raise ValueError(
                f"camera {self.camera.name!r}: image is {w}x{h} but the rig calibration is "
                f"{self.size[0]}x{self.size[1]}; set the camera to the calibrated resolution "
                f"or rescale the rig entry (K, K_rect, width, height)"
            )

    def rectify(self, image: np.ndarray) -> np.ndarray:
        """(H,W[,C]) raw image -> (H,W[,C]) rectified image (same dtype; the input itself when
        no remap is needed)."""
        if self.is_identity:
            # nothing to remap, so the size does not matter (e.g. a camera JSON without width
            # and height, whose size was guessed from the principal point)
            self.check_image(image)
            return image
        self.check_size(image)
        map1, map2 = self.maps()
        return cv2.remap(image, map1, map2, self.interpolation, borderMode=cv2.BORDER_CONSTANT)

    __call__ = rectify


def build_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables rectified px -> raw px for ``camera`` (plumb_bob / rational / equidistant)."""
    size = (camera.width, camera.height)
    if camera.is_fisheye:
        return cv2.fisheye.initUndistortRectifyMap(
            camera.K, camera.D, np.eye(3), camera.K_rect, size, cv2.CV_16SC2
        )
    return cv2.initUndistortRectifyMap(camera.K, camera.D, np.eye(3), camera.K_rect, size, cv2.CV_16SC2)
