"""Skeleton markers (``/maem/skeletons``, visualization_msgs/MarkerArray): what each person's
markers hold, computed here without rclpy; ros/wire/markers.py builds the Marker objects."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: marker namespaces; marker id = track id in each
NS_JOINTS, NS_BONES, NS_LABELS = "skeleton/joints", "skeleton/bones", "skeleton/ids"
#: namespace of the DELETEALL marker that starts every skeleton MarkerArray
NS_DELETE_ALL = "skeleton"
#: m, how far above a person's highest joint its id label floats
LABEL_LIFT_M = 0.3


@dataclass
class SkeletonPlan:
    """The markers of one frame: ``points`` (N, 3) world m, every shown finite joint once;
    per shown person k: track id ``ids[k]``, joint points ``points[first[k]:first[k + 1]]``,
    bone end points ``points[bones[k]]`` (pairs, bones with a NaN end left out) and the label
    position ``labels[k]`` (LABEL_LIFT_M above the highest joint)."""

    ids: list[int]
    points: np.ndarray
    first: np.ndarray
    bones: list[list[int]]
    labels: np.ndarray


def skeleton_plan(
    ids: Sequence[int] | np.ndarray, joints: np.ndarray, bones: Sequence[tuple[int, int]]
) -> SkeletonPlan:
    """Persons with id >= 0 and at least one finite joint, from ``joints`` (P, J, 3) world m and
    the convention's ``bones`` (joint index pairs)."""
    pj = np.asarray(joints, dtype=np.float64)  # (P, J, 3)
    pid = np.asarray(ids, dtype=np.int64)
    finite = np.asarray(np.isfinite(pj).all(axis=2))  # (P, J)
    ends = np.asarray(bones, dtype=np.intp).reshape(-1, 2)
    bone_ok: np.ndarray = finite[:, ends[:, 0]] & finite[:, ends[:, 1]]  # (P, B)
    height = np.where(finite, pj[..., 2], -np.inf)
    top = pj[np.arange(len(pj)), np.argmax(height, axis=1)] if pj.shape[1] else pj[:, :0]
    shown = np.flatnonzero((pid >= 0) & finite.any(axis=1))
    # one point per shown finite joint, shared by the joint and bone lists (the message types
    # need one Point object per point: built once)
    seen: np.ndarray = np.zeros_like(finite)
    seen[shown] = finite[shown]
    slot = np.cumsum(seen).reshape(seen.shape) - 1  # (P, J) index into points where seen
    labels = top[shown] + np.array([0.0, 0.0, LABEL_LIFT_M]) if len(shown) else np.zeros((0, 3))
    return SkeletonPlan(
        ids=pid[shown].tolist(),
        points=pj[seen],
        first=np.concatenate([[0], np.cumsum(seen[shown].sum(1))]),
        bones=[slot[p][ends[bone_ok[p]]].ravel().tolist() for p in shown.tolist()],
        labels=labels,
    )
