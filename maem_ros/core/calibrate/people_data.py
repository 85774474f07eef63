"""The detections people mode calibrates from, as dense per-camera arrays.

Frames are a common index over the cameras (frame k of every camera was stamped at the same
nominal time; any capture offset is what the time-offset step estimates). Joints are the body
and foot joints of the detections' keypoint convention (names from core.skeleton), with the
left/right permutation used to undo a detector's swapped sides.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..detections import FrameDetections
from ..geometry.camera import Rig
from ..skeleton import body_joints, convention_for

#: foot joints (their lowest point touches the floor), matched by name in any convention
FOOT_NAMES = (
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_big_toe_tip",
    "right_big_toe_tip",
    "left_foot_index",
    "right_foot_index",
)
#: head joints used for a person's height (eye height 0.936, nose ~0.91 of stature)
HEAD_NAMES = ("nose",)


@dataclass
class CameraFrames:
    """One camera's detections over the frames: for frame k, detections ``offsets[k]:
    offsets[k+1]`` of the flat arrays kpts2d (n,J,2) rectified px (NaN = not seen), kpts3d
    (n,J,3) camera-frame m, scores (n,)."""

    kpts2d: np.ndarray
    kpts3d: np.ndarray
    scores: np.ndarray
    offsets: np.ndarray

    def frame(self, k: int) -> slice:
        return slice(int(self.offsets[k]), int(self.offsets[k + 1]))

    def count(self, k: int) -> int:
        return int(self.offsets[k + 1] - self.offsets[k])

    @property
    def frame_of(self) -> np.ndarray:
        """(n,) frame index of every detection."""
        return np.repeat(np.arange(self.offsets.size - 1), np.diff(self.offsets))


@dataclass
class PeopleData:
    """Detections of every camera (rig order) over F frames, with the cameras' intrinsics.

    ``rig``: intrinsics (K_rect of the rectified px the keypoints are in); ``joints``: indices
    into the detections' keypoints of the joints used; ``names`` their names; ``flip``: (J,)
    permutation swapping left and right; ``feet`` / ``head``: positions within ``joints``.
    ``fps``: frame rate (Hz), for the time offsets.
    """

    rig: Rig
    cameras: list[CameraFrames]
    num_frames: int
    fps: float
    joints: np.ndarray
    names: tuple[str, ...]
    flip: np.ndarray
    feet: np.ndarray
    head: np.ndarray

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    def detections_per_camera(self) -> np.ndarray:
        return np.array([c.scores.size for c in self.cameras])


def joint_selection(num_joints: int) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """(joint indices, names, left/right permutation) of the body and foot joints of the
    convention with ``num_joints`` joints (all joints, no swap, if the convention is unknown)."""
    try:
        names_all = convention_for(num_joints).names
    except ValueError:
        idx = np.arange(num_joints)
        return idx, tuple(f"joint{i}" for i in idx), idx.copy()
    chosen = list(body_joints(num_joints))
    chosen += [i for i, n in enumerate(names_all) if n in FOOT_NAMES and i not in chosen]
    if "neck" in names_all and names_all.index("neck") not in chosen:
        chosen.append(names_all.index("neck"))
    idx = np.array(sorted(chosen))
    names = tuple(names_all[i] for i in idx)
    pos = {n: k for k, n in enumerate(names)}

    def mirror(n: str) -> str:
        return n.replace("left_", "@").replace("right_", "left_").replace("@", "right_")

    flip = np.array([pos.get(mirror(n), k) for k, n in enumerate(names)])
    return idx, names, flip


def people_data(rig: Rig, frames: Mapping[str, Sequence[FrameDetections | None]], fps: float) -> PeopleData:
    """PeopleData of ``frames[camera][k]`` (None or an empty FrameDetections = nothing seen)
    for the rig's cameras that have any detection; ValueError if fewer than two have people."""
    num_frames = max((len(v) for v in frames.values()), default=0)
    J = next((d.num_joints for v in frames.values() for d in v if d is not None and d.n), 0)
    if J == 0:
        raise ValueError("detections: no camera saw any person")
    joints, names, flip = joint_selection(J)
    cams, used = [], []
    for cam in rig:
        seq = list(frames.get(cam.name, []))
        seq += [None] * (num_frames - len(seq))
        counts = np.array([0 if d is None else d.n for d in seq])
        if counts.sum() == 0:
            continue
        for d in seq:
            if d is not None and d.n and d.num_joints != J:
                raise ValueError(
                    f"detections of camera {cam.name!r}: {d.num_joints} keypoints, other cameras have {J}"
                )
        present = [d for d in seq if d is not None and d.n]
        cams.append(
            CameraFrames(
                kpts2d=np.concatenate([d.kpts2d[:, joints] for d in present]),
                kpts3d=np.concatenate([d.kpts3d[:, joints] for d in present]),
                scores=np.concatenate([d.scores for d in present]),
                offsets=np.concatenate([[0], np.cumsum(counts)]),
            )
        )
        used.append(cam)
    if len(used) < 2:
        raise ValueError(
            f"detections: fewer than two cameras saw people ({', '.join(c.name for c in used) or 'none'})"
        )
    feet = np.array([k for k, n in enumerate(names) if n in FOOT_NAMES], np.int64)
    head = np.array([k for k, n in enumerate(names) if n in HEAD_NAMES], np.int64)
    return PeopleData(
        rig=Rig(used),
        cameras=cams,
        num_frames=num_frames,
        fps=float(fps),
        joints=joints,
        names=names,
        flip=flip,
        feet=feet,
        head=head,
    )


def normalised(rig: Rig, c: int, uv: np.ndarray) -> np.ndarray:
    """(...,2) rectified px of camera c -> (...,2) normalised pinhole coordinates."""
    K = rig[c].K_rect
    return (uv - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
