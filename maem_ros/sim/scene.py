"""Synthetic court scene: rig, moving people, fixed-topology meshes, detections, images, GT.

World frame: court centre, z up, metres. Detections follow the frontend contract
(FrameDetections: RECTIFIED px, MHR70 keypoints, camera-frame metres); ``raw_outputs`` gives the
same detections as SAM 3D Body dicts in RAW (distorted) px, the MAEM authors' npz layout.
Everything is deterministic per ``SceneConfig`` (seed).
"""
from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig

from .body import BodyModel, Skeleton, forward_kinematics, gait_angles
from .motion import ANGLE_FLOOR, Motion, pose_style, simulate_motion
from .noise import PRESETS, PersonState, SimDetections, get_preset, simulate
from .render import Renderer
from .rigs import load_rig


@dataclass
class SceneConfig:
    """What a scene is made of; JSON-able via to_dict/from_dict (recorded in bags and scene folders)."""

    rig: str = "sportcenter6"  # shipped rig name or a rig YAML / camera-JSON folder path
    frames: int = 90
    fps: float = 30.0
    seed: int = 0
    difficulty: str = "medium"  # none | easy | medium | hard
    num_vertices: int = 18439
    players: int = 10
    bystanders: int = 2
    start_stamp_ns: int = 1_700_000_000_000_000_000

    def __post_init__(self) -> None:
        checks = [
            ("frames", isinstance(self.frames, (int, np.integer)) and self.frames >= 1, "an integer >= 1"),
            ("fps", isinstance(self.fps, (int, float)) and np.isfinite(self.fps) and self.fps > 0,
             "a positive number"),
            ("seed", isinstance(self.seed, (int, np.integer)) and self.seed >= 0, "an integer >= 0"),
            ("difficulty", self.difficulty in PRESETS, f"one of {list(PRESETS)}"),
            ("num_vertices", isinstance(self.num_vertices, (int, np.integer)) and self.num_vertices >= 19,
             "an integer >= 19"),
            ("players", isinstance(self.players, (int, np.integer)) and self.players >= 0, "an integer >= 0"),
            ("bystanders", isinstance(self.bystanders, (int, np.integer)) and self.bystanders >= 0,
             "an integer >= 0"),
            ("start_stamp_ns",
             isinstance(self.start_stamp_ns, (int, np.integer)) and self.start_stamp_ns >= 0,
             "an integer >= 0"),
            ("rig", isinstance(self.rig, str) and bool(self.rig), "a rig name or path"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"scene config {name}: {getattr(self, name)!r} is not {want}")
        if self.players + self.bystanders < 1:
            raise ValueError("scene config players/bystanders: the scene needs at least one person")
        self.fps = float(self.fps)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SceneConfig:
        if not isinstance(d, Mapping):
            raise ValueError(f"scene config: expected a mapping, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"scene config: unknown key(s) {', '.join(unknown)}")
        values = {k: (int(v) if k in ("frames", "seed", "num_vertices", "players", "bystanders",
                                      "start_stamp_ns") and isinstance(v, float) and v.is_integer()
                      else v) for k, v in d.items()}
        return cls(**values)  # type: ignore[arg-type]  # each value is checked in __post_init__


class Scene:
    """A simulated game seen by a rig. Persons: ``players`` first, then bystanders/referees."""

    def __init__(self, config: SceneConfig | Mapping[str, Any] | None = None):
        if config is None:
            config = SceneConfig()
        elif isinstance(config, Mapping):
            config = SceneConfig.from_dict(config)
        self.config = config
        self.rig: Rig = load_rig(config.rig)
        self.num_frames = config.frames
        self.fps = config.fps
        self.noise = get_preset(config.difficulty)
        self.motion: Motion = simulate_motion(config.frames, config.fps, config.players, config.bystanders,
                                              config.seed)
        self.style = pose_style(config.frames, config.fps, config.players + config.bystanders, config.seed)
        self.body = BodyModel(config.num_vertices)
        self.is_player = np.arange(config.players + config.bystanders) < config.players
        self.team = self.motion.team
        self.num_persons = len(self.is_player)
        self._renderer = Renderer(self.body, self.team, config.seed)
        self._cache: OrderedDict[tuple, Any] = OrderedDict()

    # ---- time -----------------------------------------------------------------------------
    def _check_frame(self, frame: int) -> int:
        if not isinstance(frame, (int, np.integer)) or not 0 <= frame < self.num_frames:
            raise ValueError(f"frame: {frame!r} outside 0..{self.num_frames - 1}")
        return int(frame)

    def stamp_ns(self, frame: int) -> int:
        """Capture stamp of ``frame`` in integer nanoseconds."""
        return self.config.start_stamp_ns + int(round(self._check_frame(frame) * 1e9 / self.fps))

    def frame_at(self, stamp_ns: int) -> int | None:
        """Nearest frame to ``stamp_ns`` if within half a frame period, else None."""
        period = 1e9 / self.fps
        f = int(round((int(stamp_ns) - self.config.start_stamp_ns) / period))
        if not 0 <= f < self.num_frames:
            return None
        return f if abs(int(stamp_ns) - self.stamp_ns(f)) <= period / 2 else None

    # ---- ground truth -----------------------------------------------------------------------
    def _cached(self, key: tuple, make):
        """Memoise per kind (skeletons, meshes, detections) with a small bound: meshes are MBs each."""
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = make()
        self._cache[key] = value
        limit = {"skel": 64, "verts": 3, "det": len(self.rig) + 2}[key[0]]
        same_kind = [k for k in self._cache if k[0] == key[0]]
        for old in same_kind[:max(0, len(same_kind) - limit)]:
            del self._cache[old]
        return value

    def person_state(self, frame: int) -> PersonState:
        """Shape, root, heading and joint angles (rad) of every person at ``frame``."""
        f = self._check_frame(frame)
        m = self.motion
        angles = gait_angles(m.speed[f], m.phase[f], m.crouch[f], m.arm_raise[f], m.head_yaw[f])
        for key, offset in self.style.items():
            angles[key] = angles[key] + offset[f] * (1.0 - 0.7 * m.arm_raise[f] * key.startswith("sh_"))
        for key, floor in ANGLE_FLOOR.items():
            angles[key] = np.maximum(angles[key], floor)
        return PersonState(m.height, m.width, m.pos[f], m.heading[f], angles, self.is_player)

    def skeleton(self, frame: int) -> Skeleton:
        def make():
            s = self.person_state(frame)
            return forward_kinematics(s.height, s.width, s.angles, s.root_xy, s.heading)
        return self._cached(("skel", int(frame)), make)

    def gt_keypoints(self, frame: int) -> np.ndarray:
        """(P,70,3) MHR70 keypoints, world metres."""
        return self.skeleton(frame).keypoints.copy()

    def vertices(self, frame: int) -> np.ndarray:
        """(P,V,3) mesh vertices, world metres (vertex k = same body spot in every frame)."""
        m = self.motion
        return self._cached(("verts", int(frame)),
                            lambda: self.body.vertices(self.skeleton(frame), m.height, m.width))

    # ---- detections ---------------------------------------------------------------------------
    def _camera(self, camera: str | int) -> tuple[Camera, int]:
        cam = self.rig[camera]
        return cam, self.rig.index(cam.name)

    def simulated(self, camera: str | int, frame: int) -> SimDetections:
        """All simulated detection data of one camera/frame (incl. GT person index, -1 = false positive)."""
        cam, ci = self._camera(camera)
        f = self._check_frame(frame)

        def make():
            rng = np.random.default_rng([self.config.seed, 4242, ci, f])
            skel = self.skeleton(f)
            return simulate(cam, rng, self.noise, self.body, self.person_state(f), skel.points, gt_skel=skel)
        return self._cached(("det", ci, f), make)

    def detections(self, camera: str | int, frame: int) -> FrameDetections:
        """FrameDetections of ``camera`` at ``frame``: rectified px, MHR70, camera-frame metres."""
        d = self.simulated(camera, frame)
        cam, _ = self._camera(camera)
        # copies: callers may modify their detections, the cache must stay intact
        return FrameDetections(cam.name, self.stamp_ns(frame), d.bbox_rect.copy(), d.scores.copy(),
                               d.kpts2d_rect.copy(), d.kpts3d.copy(), d.verts2d_rect.astype(np.float32))

    def detection_persons(self, camera: str | int, frame: int) -> np.ndarray:
        """(N,) GT person index of each detection (same order as ``detections``), -1 = false positive."""
        return self.simulated(camera, frame).person.copy()

    def raw_outputs(self, camera: str | int, frame: int) -> list[dict[str, Any]]:
        """SAM 3D Body output dicts (MAEM npz layout), 2D in RAW distorted px.

        pred_keypoints_3d and pred_vertices are camera-oriented and relative to pred_cam_t (camera
        frame = value + pred_cam_t), as SAM 3D Body writes them; focal_length = fx of the raw image.
        """
        d = self.simulated(camera, frame)
        cam, _ = self._camera(camera)
        f32 = np.float32
        return [{
            "bbox": d.bbox_raw[i].astype(f32),
            "bbox_score": f32(d.scores[i]),
            "pred_keypoints_3d": (d.kpts3d[i] - d.cam_t[i]).astype(f32),
            "pred_keypoints_2d": d.kpts2d_raw[i].astype(f32),
            "pred_keypoints_2d_verts": d.verts2d_raw[i].astype(f32),
            "pred_vertices": (d.verts3d[i] - d.cam_t[i]).astype(f32),
            "pred_cam_t": d.cam_t[i].astype(f32),
            "focal_length": f32(cam.K[0, 0]),
        } for i in range(len(d.person))]

    # ---- images --------------------------------------------------------------------------------
    def render(self, camera: str | int, frame: int) -> np.ndarray:
        """(H,W,3) BGR uint8 RAW (distorted) image of ``camera`` at ``frame``."""
        cam, _ = self._camera(camera)
        f = self._check_frame(frame)
        return self._renderer.render(cam, self.vertices(f), self.skeleton(f).points)
