"""npz backend: precomputed SAM 3D Body outputs (MAEM authors' per-frame npz) replayed by stamp.

Options:
  dets_dir        a scene folder's dets/ folder, or the scene folder itself (required)
  fps             frame rate (default: the scene's scene.json, else 30)
  start_stamp_ns  stamp of frame 0 in ns (default: scene.json, else 0)
  vertex_stride   keep every n-th vertex (applied before undistortion, default 1)
Frame f of camera c is ``<dets_dir>/<c>/<f:06d>.npz`` (any file whose stem ends in the integer f);
it is picked for the stamp within half a period of start_stamp_ns + f / fps. Raw-image px in the
files are undistorted here with the rig's camera.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.interchange import (
    DEFAULT_FPS,
    MissingDataError,
    frame_at_stamp,
    index_frame_files,
    outputs_to_detections,
    read_maem_npz,
)

from .base import Estimator, option_float, option_int


class NpzEstimator(Estimator):
    """Reads ``<dets_dir>/<camera>/<frame>.npz`` for the frame nearest the stamp."""

    needs_image = False
    applies_vertex_stride = True

    def __init__(self, options: Mapping[str, Any], rig: Rig):
        if not options.get("dets_dir"):
            raise ValueError("frontend option 'dets_dir': required for the npz backend")
        root = Path(str(options["dets_dir"])).expanduser()
        if not root.is_dir():
            raise ValueError(f"frontend option 'dets_dir': {str(root)!r} is not a folder")
        self.dets_dir = root / "dets" if (root / "dets").is_dir() else root
        info = _scene_info(self.dets_dir.parent / "scene.json")
        self.fps = option_float(options, "fps", info.get("fps", DEFAULT_FPS), positive=True)
        self.start_stamp_ns = option_int(options, "start_stamp_ns", int(info.get("start_stamp_ns", 0)))
        self.vertex_stride = option_int(options, "vertex_stride", 1, minimum=1)
        self.rig = rig
        self._index: dict[str, dict[int, Path]] = {}

    def frame_at(self, stamp_ns: int) -> int | None:
        """Nearest frame within half a period, or None (before frame 0)."""
        return frame_at_stamp(stamp_ns, self.start_stamp_ns, self.fps)

    def _files(self, camera: str) -> dict[int, Path]:
        if camera not in self._index:
            self._index[camera] = index_frame_files(self.dets_dir / camera)
        return self._index[camera]

    def estimate(self, camera: Camera, stamp_ns: int, image: np.ndarray | None = None) -> FrameDetections:
        frame = self.frame_at(stamp_ns)
        if frame is None:
            raise MissingDataError(
                f"npz backend: stamp {int(stamp_ns)} ns maps to no frame of "
                f"{str(self.dets_dir)!r} (start {self.start_stamp_ns} ns, fps {self.fps})"
            )
        path = self._files(camera.name).get(frame)
        if path is None:
            self._index.pop(camera.name, None)  # files may still be arriving; look again next time
            path = self._files(camera.name).get(frame)
        if path is None:
            raise MissingDataError(
                f"npz backend: no file for camera {camera.name!r} frame {frame} "
                f"in {str(self.dets_dir / camera.name)!r}"
            )
        return outputs_to_detections(
            read_maem_npz(path),
            camera,
            int(stamp_ns),
            where=f"npz {str(path)!r} outputs",
            vertex_stride=self.vertex_stride,
        )


def _scene_info(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"scene info {str(path)!r}: unreadable JSON ({e})") from None
    return data if isinstance(data, dict) else {}
