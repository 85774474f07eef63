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
from .motion import ANGLE_FLOOR, Motion, _wrap, pose_style, simulate_motion
from .noise import PRESETS, PersonState, SimDetections, get_preset, simulate
from .render import Renderer
from .rigs import load_rig

#: s, the largest per-camera capture offset a scene simulates (the motion's warm-up is 1 s)
MAX_TIME_OFFSET_S = 0.9
#: Motion fields indexed by frame
_PER_FRAME = ("pos", "speed", "heading", "phase", "crouch", "arm_raise", "head_yaw")


def _with_time_offsets(rig: Rig, offsets: Mapping[str, float]) -> Rig:
    """The rig with each named camera's time_offset set (the scene's ground truth)."""
    unknown = sorted(set(offsets) - set(rig.names))
    if unknown:
        raise ValueError(f"scene config time_offsets: unknown camera(s) {unknown}; the rig has {rig.names}")
    return Rig([dataclasses.replace(c, time_offset=offsets.get(c.name, c.time_offset)) for c in rig])


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
    #: camera -> s: that camera captures frame k at stamp(k) + offset (it samples the motion at
    #: its own time while stamping the nominal time); written into the scene's rig as
    #: Camera.time_offset. |offset| < MAX_TIME_OFFSET_S
    time_offsets: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        checks = [
            ("frames", isinstance(self.frames, (int, np.integer)) and self.frames >= 1, "an integer >= 1"),
            (
                "fps",
                isinstance(self.fps, (int, float)) and np.isfinite(self.fps) and self.fps > 0,
                "a positive number",
            ),
            ("seed", isinstance(self.seed, (int, np.integer)) and self.seed >= 0, "an integer >= 0"),
            ("difficulty", self.difficulty in PRESETS, f"one of {list(PRESETS)}"),
            (
                "num_vertices",
                isinstance(self.num_vertices, (int, np.integer)) and self.num_vertices >= 19,
                "an integer >= 19",
            ),
            ("players", isinstance(self.players, (int, np.integer)) and self.players >= 0, "an integer >= 0"),
            (
                "bystanders",
                isinstance(self.bystanders, (int, np.integer)) and self.bystanders >= 0,
                "an integer >= 0",
            ),
            (
                "start_stamp_ns",
                isinstance(self.start_stamp_ns, (int, np.integer)) and self.start_stamp_ns >= 0,
                "an integer >= 0",
            ),
            ("rig", isinstance(self.rig, str) and bool(self.rig), "a rig name or path"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"scene config {name}: {getattr(self, name)!r} is not {want}")
        if not isinstance(self.time_offsets, Mapping) or not all(
            isinstance(v, (int, float)) and np.isfinite(v) and abs(v) < MAX_TIME_OFFSET_S
            for v in self.time_offsets.values()
        ):
            raise ValueError(
                f"scene config time_offsets: {self.time_offsets!r} is not a mapping "
                f"camera -> seconds within +-{MAX_TIME_OFFSET_S}"
            )
        self.time_offsets = {str(k): float(v) for k, v in self.time_offsets.items()}
        if self.players + self.bystanders < 1:
            raise ValueError("scene config players/bystanders: the scene needs at least one person")
        self.fps = float(self.fps)

    def to_dict(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if not out["time_offsets"]:  # recorded only when used: older readers know no such key
            del out["time_offsets"]
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SceneConfig:
        if not isinstance(d, Mapping):
            raise ValueError(f"scene config: expected a mapping, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"scene config: unknown key(s) {', '.join(unknown)}")
        values = {
            k: (
                int(v)
                if k in ("frames", "seed", "num_vertices", "players", "bystanders", "start_stamp_ns")
                and isinstance(v, float)
                and v.is_integer()
                else v
            )
            for k, v in d.items()
        }
        return cls(**values)  # type: ignore[arg-type]  # each value is checked in __post_init__


class Scene:
    """A simulated game seen by a rig. Persons: ``players`` first, then bystanders/referees."""

    def __init__(self, config: SceneConfig | Mapping[str, Any] | None = None):
        if config is None:
            config = SceneConfig()
        elif isinstance(config, Mapping):
            config = SceneConfig.from_dict(config)
        self.config = config
        self.rig: Rig = _with_time_offsets(load_rig(config.rig), config.time_offsets)
        self.num_frames = config.frames
        self.fps = config.fps
        self.noise = get_preset(config.difficulty)
        # frames kept before 0 and after the last for cameras capturing off the nominal time
        pad = int(np.ceil(max(map(abs, config.time_offsets.values()), default=0.0) * config.fps))
        pad += bool(pad)
        self._lead = pad
        persons = config.players + config.bystanders
        self._motion = simulate_motion(
            config.frames + pad, config.fps, config.players, config.bystanders, config.seed, lead=pad
        )
        self._style = pose_style(config.frames + 2 * pad, config.fps, persons, config.seed, first_frame=-pad)
        frames = slice(pad, pad + config.frames)
        self.motion: Motion = dataclasses.replace(
            self._motion, **{k: getattr(self._motion, k)[frames] for k in _PER_FRAME}
        )
        self.style = {k: v[frames] for k, v in self._style.items()}
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
        for old in same_kind[: max(0, len(same_kind) - limit)]:
            del self._cache[old]
        return value

    def capture_position(self, camera: str | int, frame: int) -> float:
        """Where in time (fractional frame index) ``camera`` captures ``frame``: frame +
        its time offset x fps."""
        return self._check_frame(frame) + self.rig[camera].time_offset * self.fps

    def _at(self, values: np.ndarray, position: float, angle: bool = False) -> np.ndarray:
        """(F+2 pad, ...) per-frame values at a fractional frame index (linear; angles along
        the shorter arc)."""
        x = position + self._lead
        i = int(np.floor(x))
        w = x - i
        if w == 0.0:
            return values[i]
        step = values[i + 1] - values[i]
        return values[i] + w * (_wrap(step) if angle else step)

    def person_state(self, frame: int | float) -> PersonState:
        """Shape, root, heading and joint angles (rad) of every person at ``frame`` (a
        fractional frame index between frames: the motion interpolated)."""
        f = self._check_frame(frame) if isinstance(frame, (int, np.integer)) else float(frame)
        m, at = self._motion, self._at
        arm = at(m.arm_raise, f)
        angles = gait_angles(at(m.speed, f), at(m.phase, f, True), at(m.crouch, f), arm, at(m.head_yaw, f))
        for key, offset in self._style.items():
            angles[key] = angles[key] + at(offset, f) * (1.0 - 0.7 * arm * key.startswith("sh_"))
        for key, floor in ANGLE_FLOOR.items():
            angles[key] = np.maximum(angles[key], floor)
        return PersonState(m.height, m.width, at(m.pos, f), at(m.heading, f, True), angles, self.is_player)

    def skeleton(self, frame: int | float) -> Skeleton:
        def make():
            s = self.person_state(frame)
            return forward_kinematics(s.height, s.width, s.angles, s.root_xy, s.heading)

        key = int(frame) if isinstance(frame, (int, np.integer)) else float(frame)
        return self._cached(("skel", key), make)

    def gt_keypoints(self, frame: int) -> np.ndarray:
        """(P,70,3) MHR70 keypoints, world metres."""
        return self.skeleton(frame).keypoints.copy()

    def vertices(self, frame: int | float) -> np.ndarray:
        """(P,V,3) mesh vertices, world metres (vertex k = same body spot in every frame)."""
        m = self.motion
        key = int(frame) if isinstance(frame, (int, np.integer)) else float(frame)
        return self._cached(
            ("verts", key), lambda: self.body.vertices(self.skeleton(frame), m.height, m.width)
        )

    def _captured(self, camera: str | int, frame: int) -> int | float:
        """The frame position ``camera`` samples for ``frame`` (the frame itself without an
        offset, so synchronised scenes stay exactly as before)."""
        position = self.capture_position(camera, frame)
        return int(frame) if position == int(frame) else position

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
            at = self._captured(camera, f)
            skel = self.skeleton(at)
            return simulate(cam, rng, self.noise, self.body, self.person_state(at), skel.points, gt_skel=skel)

        return self._cached(("det", ci, f), make)

    def detections(self, camera: str | int, frame: int) -> FrameDetections:
        """FrameDetections of ``camera`` at ``frame``: rectified px, MHR70, camera-frame metres."""
        d = self.simulated(camera, frame)
        cam, _ = self._camera(camera)
        # copies: callers may modify their detections, the cache must stay intact
        return FrameDetections(
            cam.name,
            self.stamp_ns(frame),
            d.bbox_rect.copy(),
            d.scores.copy(),
            d.kpts2d_rect.copy(),
            d.kpts3d.copy(),
            d.verts2d_rect.astype(np.float32),
        )

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
        return [
            {
                "bbox": d.bbox_raw[i].astype(f32),
                "bbox_score": f32(d.scores[i]),
                "pred_keypoints_3d": (d.kpts3d[i] - d.cam_t[i]).astype(f32),
                "pred_keypoints_2d": d.kpts2d_raw[i].astype(f32),
                "pred_keypoints_2d_verts": d.verts2d_raw[i].astype(f32),
                "pred_vertices": (d.verts3d[i] - d.cam_t[i]).astype(f32),
                "pred_cam_t": d.cam_t[i].astype(f32),
                "focal_length": f32(cam.K[0, 0]),
            }
            for i in range(len(d.person))
        ]

    # ---- images --------------------------------------------------------------------------------
    def render(self, camera: str | int, frame: int) -> np.ndarray:
        """(H,W,3) BGR uint8 RAW (distorted) image of ``camera`` at ``frame``."""
        cam, _ = self._camera(camera)
        f = self._check_frame(frame)
        at = self._captured(camera, f)
        return self._renderer.render(cam, self.vertices(at), self.skeleton(at).points)
