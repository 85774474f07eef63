"""Keypoint conventions (names, index maps from MHR70, name-based conversion) and bones.

mhr70 (SAM 3D Body), sportcenter_13 and coco_17 (subsets of MHR70) and blazepose_33 (MediaPipe
Pose: its own 33 landmarks, not an MHR70 subset). Conversion between any two goes by joint name
(``convert``); a target joint the source lacks is a ValueError, never a zero.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import numpy as np


def _hand(side: str) -> list[str]:
    # SAM 3D Body orders each hand finger by finger, tip first, then the wrist.
    return [
        f"{side}_{finger}_{part}"
        for finger in ("thumb", "index", "middle", "ring", "pinky")
        for part in ("tip", "first_joint", "second_joint", "third_joint")
    ] + [f"{side}_wrist"]


MHR70_NAMES: tuple[str, ...] = tuple(
    [
        "nose",
        "left_eye",
        "right_eye",
        "left_ear",
        "right_ear",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
        "left_big_toe_tip",
        "left_small_toe_tip",
        "left_heel",
        "right_big_toe_tip",
        "right_small_toe_tip",
        "right_heel",
    ]
    + _hand("right")
    + _hand("left")
    + [
        "left_olecranon",
        "right_olecranon",
        "left_cubital_fossa",
        "right_cubital_fossa",
        "left_acromion",
        "right_acromion",
        "neck",
    ]
)
assert len(MHR70_NAMES) == 70


def _bones(names: tuple[str, ...], pairs: list[tuple[str, str]]) -> tuple[tuple[int, int], ...]:
    idx = {n: i for i, n in enumerate(names)}
    return tuple((idx[a], idx[b]) for a, b in pairs if a in idx and b in idx)


_BODY_BONES = [
    ("nose", "left_eye"),
    ("nose", "right_eye"),
    ("left_eye", "left_ear"),
    ("right_eye", "right_ear"),
    ("nose", "neck"),
    ("neck", "left_shoulder"),
    ("neck", "right_shoulder"),
    ("left_shoulder", "right_shoulder"),
    ("left_shoulder", "left_elbow"),
    ("left_elbow", "left_wrist"),
    ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"),
    ("left_shoulder", "left_hip"),
    ("right_shoulder", "right_hip"),
    ("left_hip", "right_hip"),
    ("left_hip", "left_knee"),
    ("left_knee", "left_ankle"),
    ("right_hip", "right_knee"),
    ("right_knee", "right_ankle"),
    ("left_ankle", "left_heel"),
    ("left_ankle", "left_big_toe_tip"),
    ("left_ankle", "left_small_toe_tip"),
    ("right_ankle", "right_heel"),
    ("right_ankle", "right_big_toe_tip"),
    ("right_ankle", "right_small_toe_tip"),
]
_HAND_BONES = [
    (f"{s}_wrist", f"{s}_{f}_third_joint")
    for s in ("left", "right")
    for f in ("thumb", "index", "middle", "ring", "pinky")
] + [
    (f"{s}_{f}_{a}", f"{s}_{f}_{b}")
    for s in ("left", "right")
    for f in ("thumb", "index", "middle", "ring", "pinky")
    for a, b in (("third_joint", "second_joint"), ("second_joint", "first_joint"), ("first_joint", "tip"))
]


@dataclass(frozen=True)
class KeypointConvention:
    """A keypoint set: names, the MHR70 index of each (None when not an MHR70 subset), bones as
    index pairs."""

    name: str
    names: tuple[str, ...]
    from_mhr70: tuple[int, ...] | None
    bones: tuple[tuple[int, int], ...]

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def select(self, mhr70: np.ndarray, axis: int = -2) -> np.ndarray:
        """Pick this convention's joints out of an MHR70 array along ``axis`` (default: (...,70,D))."""
        if self.from_mhr70 is None:
            raise ValueError(f"keypoints: {self.name} is not a subset of mhr70; use convert")
        if mhr70.shape[axis] != 70:
            raise ValueError(f"keypoints: expected 70 MHR70 joints on axis {axis}, got {mhr70.shape[axis]}")
        return np.take(mhr70, self.from_mhr70, axis=axis)

    def indices_in(self, source: KeypointConvention) -> tuple[int, ...]:
        """Index in ``source`` of each of this convention's joints (matched by name)."""
        idx = {n: i for i, n in enumerate(source.names)}
        missing = [n for n in self.names if n not in idx]
        if missing:
            raise ValueError(
                f"keypoints: cannot convert {source.name} to {self.name}: "
                f"{source.name} has no {', '.join(missing)}"
            )
        return tuple(idx[n] for n in self.names)


SPORTCENTER_13_FROM_MHR70 = (0, 5, 6, 7, 8, 62, 41, 9, 10, 11, 12, 13, 14)

MHR70 = KeypointConvention(
    "mhr70", MHR70_NAMES, tuple(range(70)), _bones(MHR70_NAMES, _BODY_BONES + _HAND_BONES)
)
_SC13_NAMES = tuple(MHR70_NAMES[i] for i in SPORTCENTER_13_FROM_MHR70)
SPORTCENTER_13 = KeypointConvention(
    "sportcenter_13",
    _SC13_NAMES,
    SPORTCENTER_13_FROM_MHR70,
    _bones(_SC13_NAMES, _BODY_BONES + [("nose", "left_shoulder"), ("nose", "right_shoulder")]),
)
_COCO17_FROM_MHR70 = (0, 1, 2, 3, 4, 5, 6, 7, 8, 62, 41, 9, 10, 11, 12, 13, 14)
_COCO17_NAMES = tuple(MHR70_NAMES[i] for i in _COCO17_FROM_MHR70)
COCO_17 = KeypointConvention("coco_17", _COCO17_NAMES, _COCO17_FROM_MHR70, _bones(_COCO17_NAMES, _BODY_BONES))

#: MediaPipe Pose (BlazePose) landmark order, as mp.solutions.pose.PoseLandmark
BLAZEPOSE_33_NAMES: tuple[str, ...] = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)
#: mp.solutions.pose.POSE_CONNECTIONS
_BLAZEPOSE_BONES = [
    ("nose", "left_eye_inner"),
    ("left_eye_inner", "left_eye"),
    ("left_eye", "left_eye_outer"),
    ("left_eye_outer", "left_ear"),
    ("nose", "right_eye_inner"),
    ("right_eye_inner", "right_eye"),
    ("right_eye", "right_eye_outer"),
    ("right_eye_outer", "right_ear"),
    ("mouth_left", "mouth_right"),
    ("left_shoulder", "right_shoulder"),
    ("left_shoulder", "left_hip"),
    ("right_shoulder", "right_hip"),
    ("left_hip", "right_hip"),
] + [
    (f"{s}_{a}", f"{s}_{b}")
    for s in ("left", "right")
    for a, b in (
        ("shoulder", "elbow"),
        ("elbow", "wrist"),
        ("wrist", "pinky"),
        ("wrist", "index"),
        ("wrist", "thumb"),
        ("pinky", "index"),
        ("hip", "knee"),
        ("knee", "ankle"),
        ("ankle", "heel"),
        ("heel", "foot_index"),
        ("ankle", "foot_index"),
    )
]
BLAZEPOSE_33 = KeypointConvention(
    "blazepose_33", BLAZEPOSE_33_NAMES, None, _bones(BLAZEPOSE_33_NAMES, _BLAZEPOSE_BONES)
)

CONVENTIONS: dict[str, KeypointConvention] = {
    c.name: c for c in (MHR70, SPORTCENTER_13, COCO_17, BLAZEPOSE_33)
}


def get_convention(name: str) -> KeypointConvention:
    try:
        return CONVENTIONS[name]
    except KeyError:
        raise ValueError(
            f"keypoint convention: unknown {name!r}, expected one of {sorted(CONVENTIONS)}"
        ) from None


def convention_for(num_joints: int) -> KeypointConvention:
    """The convention with this many joints (for drawing data whose convention is implicit)."""
    for conv in CONVENTIONS.values():
        if conv.num_joints == num_joints:
            return conv
    raise ValueError(f"keypoint convention: none has {num_joints} joints")


def body_joints(num_joints: int) -> tuple[int, ...]:
    """Indices of the sportcenter_13 body joints (head, shoulders, elbows, wrists, hips, knees,
    ankles) within the convention that has ``num_joints`` joints, matched by name; all joints
    when no convention has that count or it names none of them."""
    try:
        conv = convention_for(num_joints)
    except ValueError:
        return tuple(range(num_joints))
    where = {n: i for i, n in enumerate(conv.names)}
    picked = tuple(where[n] for n in SPORTCENTER_13.names if n in where)
    return picked if len(picked) >= 3 else tuple(range(num_joints))


def convert(joints: np.ndarray, target: KeypointConvention, source: str | None = None) -> np.ndarray:
    """(...,J,D) keypoints in convention ``source`` (default: the one with J joints) -> target.

    The one keypoint-convention conversion: identity when the source is the target (or has
    its joint count and no name is given), MHR70 -> any convention by its index map, any
    other pair by joint name (e.g. blazepose_33 -> sportcenter_13); ValueError naming both
    conventions when the source lacks one of the target's joints.
    """
    j = joints.shape[-2]
    if source is None:
        if j == target.num_joints:
            return joints
        try:
            source = convention_for(j).name
        except ValueError:
            raise ValueError(
                f"keypoints: cannot map {j} joints (unknown convention) to {target.name}"
            ) from None
    if source == target.name and j == target.num_joints:
        return joints
    if source == MHR70.name and j == MHR70.num_joints and target.from_mhr70 is not None:
        return target.select(joints)
    src = get_convention(source)
    if j != src.num_joints:
        raise ValueError(
            f"keypoints: cannot map {j} joints (convention {source!r}, "
            f"{src.num_joints} joints) to {target.name}"
        )
    return np.take(joints, target.indices_in(src), axis=-2)


@overload
def joint_subset(spec: object, num_joints: int) -> np.ndarray: ...


@overload
def joint_subset(spec: object, num_joints: None) -> np.ndarray | None: ...


def joint_subset(spec: object, num_joints: int | None) -> np.ndarray | None:
    """Keypoint indices named by ``spec`` for ``num_joints`` keypoints (None: only check ``spec``;
    then None for "body" and "all", whose indices depend on the keypoint count).

    "body": the sportcenter_13 body joints of the convention with that many joints (all when
    none is known); "all"; or comma-separated indices. ValueError naming cost_joints.
    """
    if not isinstance(spec, str):
        raise ValueError(f"cost_joints: expected 'body', 'all' or comma-separated indices, got {spec!r}")
    if spec in ("body", "all"):
        if num_joints is None:
            return None
        return np.arange(num_joints) if spec == "all" else np.asarray(body_joints(num_joints))
    try:
        idx = np.array([int(x) for x in spec.split(",")], dtype=np.int64)
    except ValueError:
        raise ValueError(
            f"cost_joints: expected 'body', 'all' or comma-separated indices, got {spec!r}"
        ) from None
    if idx.size < 3 or np.unique(idx).size != idx.size or idx.min() < 0:
        raise ValueError(f"cost_joints: need >= 3 distinct non-negative indices, got {spec!r}")
    if num_joints is not None and idx.max() >= num_joints:
        raise ValueError(f"cost_joints: index {int(idx.max())} out of range for {num_joints} keypoints")
    return idx
