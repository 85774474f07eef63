"""synthetic backend: the simulator's SAM 3D Body noise model on a regenerated sim scene.

Options (scene config, all optional; defaults are SceneConfig's):
  scene_dict      a SceneConfig.to_dict() mapping or its JSON string (as recorded in bags and in
                  a scene folder's scene.json); when given, the keys below override it
  rig, seed, difficulty, frames, fps, start_stamp_ns, num_vertices
The scene is deterministic per config, so the frontend reproduces exactly the detections of
``maem-sim`` / the bag it was recorded with. A stamp that maps to no scene frame is a ValueError.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig

from .base import Estimator

#: frontend option -> SceneConfig field
_CONFIG_KEYS = {
    "rig": "rig",
    "seed": "seed",
    "difficulty": "difficulty",
    "frames": "frames",
    "fps": "fps",
    "start_stamp_ns": "start_stamp_ns",
    "num_vertices": "num_vertices",
}


def scene_config_dict(options: Mapping[str, Any]) -> dict[str, Any]:
    """The SceneConfig dict described by frontend options (scene_dict, then explicit keys)."""
    base = options.get("scene_dict") or {}
    if isinstance(base, str):
        try:
            base = json.loads(base)
        except json.JSONDecodeError as e:
            raise ValueError(f"frontend option 'scene_dict': not valid JSON ({e})") from None
    if not isinstance(base, Mapping):
        raise ValueError(f"frontend option 'scene_dict': expected a mapping, got {type(base).__name__}")
    # scene.json nests the config; accept that layout too
    out = dict(base.get("scene_config", base))
    for key, field in _CONFIG_KEYS.items():
        if key in options and options[key] not in (None, ""):
            out[field] = options[key]
    return out


class SyntheticEstimator(Estimator):
    """Detections of a simulated scene for (camera, stamp); the image is not used."""

    needs_image = False

    def __init__(self, options: Mapping[str, Any], rig: Rig):
        from ..sim.scene import Scene, SceneConfig  # the simulator is heavy; load only when used

        self.config = SceneConfig.from_dict(scene_config_dict(options))
        self.scene = Scene(self.config)
        unknown = [n for n in rig.names if n not in self.scene.rig]
        if unknown:
            raise ValueError(
                f"synthetic backend: rig cameras {unknown} are not in scene rig "
                f"{self.config.rig!r} ({self.scene.rig.names})"
            )

    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None = None) -> FrameDetections:
        frame = self.scene.frame_at(int(stamp_ns))
        if frame is None:
            raise ValueError(
                f"synthetic backend: stamp {int(stamp_ns)} ns is not a frame of the scene "
                f"({self.scene.num_frames} frames from {self.scene.stamp_ns(0)} ns)"
            )
        if camera.name not in self.scene.rig:
            raise ValueError(
                f"synthetic backend: camera {camera.name!r} is not in the scene rig {self.scene.rig.names}"
            )
        # the capture stamp asked for, not the frame's nominal one (they differ by < half a period)
        return dataclasses.replace(self.scene.detections(camera.name, frame), stamp_ns=int(stamp_ns))
