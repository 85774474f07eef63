"""Small bags with known content for the export and Foxglove tests (written with the project's
bag writer and wire encoders, as the triangulation node and maem-make-bag would)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from maem_ros.core.geometry.camera import Rig
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.ros import wire
from maem_ros import bagio

T0_NS = 1_700_000_000_000_000_000
FPS = 30.0
STEP_NS = 33_333_333


@dataclass
class KnownPoses:
    """What was written: per message (stamp, ids, joints (P,J,3) world m, NaN = missing)."""

    frames: list[tuple[int, np.ndarray, np.ndarray]]
    rig: Rig


def two_camera_rig() -> Rig:
    """The first two cameras of the shipped sportcenter6 rig."""
    from maem_ros.params import resolve_rig_path

    full = Rig.load(resolve_rig_path("sportcenter6"))
    return Rig([full[0], full[1]])


def read_poses(path: Path, topic: str) -> list:
    """The decoded poses messages (wire.PoseFrame) of ``topic`` in a bag, in log-time order."""
    return [wire.msg_to_poses(m.decode(), topic) for m in bagio.read_messages(path, [topic])]


def known_frames(num_frames: int = 10, dropped: tuple[int, ...] = (6,),
                 seed: int = 0) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Tracks 3 and 7 in every frame (a few NaN joints), track 12 in frames 2-3 only, one
    untracked person in every frame; grid frames in ``dropped`` have no message."""
    rng = np.random.default_rng(seed)
    j = SPORTCENTER_13.num_joints
    base = np.column_stack([rng.uniform(-0.3, 0.3, j), rng.uniform(-0.2, 0.2, j),
                            np.linspace(1.7, 0.1, j)])
    frames = []
    for k in range(num_frames):
        if k in dropped:
            continue
        ids = [3, 7, wire.UNTRACKED_ID] + ([12] if k in (2, 3) else [])
        centres = {3: (-2.0, 1.0), 7: (3.0, -2.0), wire.UNTRACKED_ID: (0.0, 4.0), 12: (6.0, 2.0)}
        joints = np.stack([base + [centres[i][0] + 0.05 * k, centres[i][1], 0.0]
                           + rng.normal(0, 0.01, (j, 3)) for i in ids])
        if k == 1:
            joints[0, 4] = np.nan  # track 3 loses right_elbow
        if k == 4:
            joints[1, [0, 11]] = np.nan
        frames.append((T0_NS + k * STEP_NS, np.asarray(ids, dtype=np.int64), joints))
    return frames


def write_poses_bag(path: Path, frames, rig: Rig | None = None, images: bool = False,
                    topic: str = "/maem/poses", store_rig: bool = True,
                    malformed: Sequence[int] = ()) -> KnownPoses:
    """A rosbag2 folder with ``topic`` (poses layout); with ``images`` also per camera of
    ``rig`` (default two_camera_rig()) a JPEG /<cam>/image_raw/compressed and /<cam>/camera_info
    at every stamp; with ``store_rig`` the rig YAML in custom data (as maem-make-bag writes it;
    a maem-record bag has none). Messages ``malformed`` (indices into ``frames``) are written as
    a PointCloud2 without fields."""
    rig = rig if rig is not None else two_camera_rig()
    with bagio.BagWriter(path) as bag:
        for n, (stamp, ids, joints) in enumerate(frames):
            msg = wire.poses_to_msg(stamp, "world", ids, joints, np.full(len(ids), 2),
                                    np.full(len(ids), 0.9))
            if n in malformed:
                msg.fields = []
            bag.write(topic, msg, stamp)
            if images:
                for cam in rig:
                    img = np.full((cam.height, cam.width, 3), 90, np.uint8)
                    ok, jpg = cv2.imencode(".jpg", img)
                    assert ok
                    bag.write(f"/{cam.name}/image_raw/compressed",
                              wire.compressed_image_msg(jpg.tobytes(), "jpeg", stamp, cam.name),
                              stamp)
                    bag.write(f"/{cam.name}/camera_info",
                              wire.camera_info_msg(cam, stamp, cam.name), stamp)
        if store_rig:
            tmp = path.parent / f"{path.name}.rig.yaml"
            rig.to_yaml(tmp)
            bag.set_custom(bagio.CUSTOM_RIG, tmp.read_text())
            tmp.unlink()
    return KnownPoses(list(frames), rig)
