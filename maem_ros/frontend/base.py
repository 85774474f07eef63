"""The estimator interface: one camera, one image (or stamp) -> FrameDetections in rectified px.

Backends (``make_estimator(backend, options, rig)``):
  synthetic   the simulator's detection-noise model on a regenerated sim scene (no image needed)
  npz         precomputed SAM 3D Body outputs in the MAEM authors' npz layout (no image needed)
  sam3d_body  the official SAM 3D Body model (needs images; imported lazily)
  mediapipe   multi-person BlazePose-33 from the mediapipe wheel, CPU, no mesh (V = 0; optional
              extra, imported lazily)

Options common to every backend:
  vertex_stride (int, default 1)  keep every n-th mesh vertex of verts2d (bandwidth / CPU).
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig


class Estimator(ABC):
    """Per-camera monocular mesh-recovery frontend."""

    #: True when estimate() needs the image (else it may be called with image=None)
    needs_image: bool = True
    #: True when the backend applies the ``vertex_stride`` option itself (cheaper than wrapping)
    applies_vertex_stride: bool = False

    @abstractmethod
    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None) -> FrameDetections:
        """Detections of ``camera`` at ``stamp_ns`` (ns), 2D in the camera's RECTIFIED px.

        ``image`` is the RECTIFIED BGR uint8 (H,W,3) frame (frontend.rectify.Rectifier, K_rect)
        when ``needs_image``, else None; ValueError on bad input.
        """


class StridedEstimator(Estimator):
    """Wraps an estimator and keeps every ``stride``-th mesh vertex (vertex k -> k*stride)."""

    def __init__(self, inner: Estimator, stride: int):
        if int(stride) < 1:
            raise ValueError(f"vertex_stride: must be >= 1, got {stride}")
        self.inner = inner
        self.stride = int(stride)
        self.needs_image = inner.needs_image

    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None) -> FrameDetections:
        dets = self.inner.estimate(camera, stamp_ns, image)
        # a new object (the inner backend may cache what it returned), the subset announced
        return dets.with_vertex_subset(self.stride)


#: backend name -> "module:Class" (imported on demand so a missing optional dependency of one
#: backend never breaks the others)
_BACKENDS: dict[str, str | Callable[[Mapping[str, Any], Rig], Estimator]] = {
    "synthetic": "maem_ros.frontend.synthetic:SyntheticEstimator",
    "npz": "maem_ros.frontend.npz:NpzEstimator",
    "sam3d_body": "maem_ros.frontend.sam3d_body:Sam3dBodyEstimator",
    "mediapipe": "maem_ros.frontend.mediapipe_pose:MediapipeEstimator",
}


def register_backend(name: str, factory: Callable[[Mapping[str, Any], Rig], Estimator]) -> None:
    """Add a backend: ``factory(options, rig) -> Estimator``."""
    _BACKENDS[name] = factory


def backends() -> list[str]:
    return sorted(_BACKENDS)


def _factory(backend: str) -> Callable[[Mapping[str, Any], Rig], Estimator]:
    entry = _BACKENDS.get(backend)
    if entry is None:
        raise ValueError(f"frontend backend: unknown {backend!r}, expected one of {backends()}")
    if callable(entry):
        return entry
    module, _, cls = entry.partition(":")
    return getattr(importlib.import_module(module), cls)


def _exact_int(value: Any) -> int | None:
    """``value`` as an exact int (no float round trip: ns stamps exceed 2^53), else None."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return int(value) if float(value).is_integer() else None
    if isinstance(value, str):
        try:
            return int(value.strip())
        except ValueError:
            return None
    return None


def option_int(options: Mapping[str, Any], key: str, default: int, minimum: int | None = None) -> int:
    """An integer option (ValueError naming it when not an integer or below ``minimum``)."""
    value = options.get(key, default)
    out = _exact_int(value)
    if out is None:
        raise ValueError(f"frontend option {key!r}: expected an integer, got {value!r}")
    if minimum is not None and out < minimum:
        raise ValueError(f"frontend option {key!r}: must be >= {minimum}, got {out}")
    return out


def option_float(options: Mapping[str, Any], key: str, default: float, positive: bool = False) -> float:
    """A float option (ValueError naming it when not a finite number, or not > 0 if ``positive``)."""
    value = options.get(key, default)
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"frontend option {key!r}: expected a number, got {value!r}") from None
    if not np.isfinite(out) or (positive and out <= 0):
        raise ValueError(
            f"frontend option {key!r}: expected a finite{' positive' if positive else ''} "
            f"number, got {value!r}"
        )
    return out


def check_bgr_image(image: Any, backend: str, camera: str) -> np.ndarray:
    """``image`` when it is a BGR uint8 (H,W,3) array, else ValueError naming backend and camera."""
    if (
        image is None
        or not isinstance(image, np.ndarray)
        or image.ndim != 3
        or image.shape[2] != 3
        or image.dtype != np.uint8
    ):
        raise ValueError(
            f"{backend} backend: camera {camera!r}: expected a BGR uint8 "
            f"(H,W,3) image, got {getattr(image, 'shape', type(image).__name__)} "
            f"{getattr(image, 'dtype', '')}"
        )
    return image


def make_estimator(backend: str, options: Mapping[str, Any], rig: Rig) -> Estimator:
    """Build a backend from its options (unknown keys are ignored: the node passes all its params)."""
    options = dict(options or {})
    stride = option_int(options, "vertex_stride", 1, minimum=1)
    estimator = _factory(backend)(options, rig)
    if stride > 1 and not estimator.applies_vertex_stride:
        return StridedEstimator(estimator, stride)
    return estimator
