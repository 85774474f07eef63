"""Poses (``/maem/poses``): one point per person, with the optional ``joint_std`` field. No
rclpy."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from maem_ros.wire.cdr import to_rosbags
from maem_ros.wire.cloud import (
    F32,
    U16,
    U32,
    Cloud,
    WireError,
    check_finite,
    checked_stamp_ns,
    count_of,
    field_of,
    new_cloud,
    view_cloud,
)

#: poses ``id`` of a person whose track is not confirmed yet
UNTRACKED_ID = 0xFFFFFFFF
POSE_TYPES = {"id": U32, "joints": F32, "views": U16, "score": F32}
POSE_OPTIONAL = {"joint_std": F32}


@dataclass
class PoseFrame:
    """Decoded /maem/poses: ids (P,) int64, joints (P,J,3) world m (NaN = missing), views, scores,
    joint_std (P,J) m or None when the message has no ``joint_std`` field."""

    stamp_ns: int
    frame_id: str
    ids: np.ndarray
    joints: np.ndarray
    views: np.ndarray
    scores: np.ndarray
    joint_std: np.ndarray | None = None


def poses_to_cloud(
    stamp_ns: int,
    frame_id: str,
    ids: np.ndarray,
    joints: np.ndarray,
    views: np.ndarray,
    scores: np.ndarray,
    joint_std: np.ndarray | None = None,
) -> Cloud:
    """Persons -> PointCloud2; ids < 0 (tentative tracks) are sent as UNTRACKED_ID; the
    ``joint_std`` field (P,J) m is written when given."""
    joints = np.asarray(joints, dtype=np.float64)
    p = int(joints.shape[0])
    j = int(joints.shape[1]) if joints.ndim == 3 else 0
    fields = [("id", U32, 1), ("joints", F32, 3 * j), ("views", U16, 1), ("score", F32, 1)]
    if joint_std is not None:
        fields.append(("joint_std", F32, j))
    msg, rec = new_cloud(stamp_ns, frame_id, fields, p)
    if p:
        ids = np.asarray(ids, dtype=np.int64)
        rec["id"] = np.where(ids < 0, UNTRACKED_ID, ids).astype(np.uint32)
        rec["joints"] = joints.reshape(p, 3 * j)
        rec["views"] = np.clip(np.asarray(views), 0, 65535).astype(np.uint16)
        rec["score"] = np.asarray(scores, dtype=np.float32)
        if joint_std is not None:
            rec["joint_std"] = np.asarray(joint_std, dtype=np.float32).reshape(p, j)
    return msg


def msg_to_poses(msg: Any, topic: str) -> PoseFrame:
    """PointCloud2 -> PoseFrame (NaN joints allowed, inf not)."""
    rec = view_cloud(msg, topic, POSE_TYPES, POSE_OPTIONAL)
    for name in ("id", "views", "score"):
        if count_of(msg, name) != 1:
            raise WireError(topic, name, f"count {count_of(msg, name)}, expected 1", "bad_count")
    c3 = count_of(msg, "joints")
    if c3 % 3:
        raise WireError(topic, "joints", f"count {c3}, expected 3J", "bad_count")
    f = {name: field_of(rec, name) for name in POSE_TYPES}
    check_finite(topic, "joints", f["joints"], "person", allow_nan=True)
    check_finite(topic, "score", f["score"], "person")
    n = len(rec)
    return PoseFrame(
        stamp_ns=checked_stamp_ns(msg.header.stamp, topic),
        frame_id=msg.header.frame_id,
        ids=f["id"][:, 0].astype(np.int64),
        joints=f["joints"].reshape(n, c3 // 3, 3).astype(np.float64),
        views=f["views"][:, 0].astype(np.int64),
        scores=f["score"][:, 0].astype(np.float64),
        joint_std=_pose_joint_std(msg, rec, topic, c3 // 3),
    )


def _pose_joint_std(msg: Any, rec: np.ndarray, topic: str, j: int) -> np.ndarray | None:
    """The optional ``joint_std`` field (P,J) m of a poses message, None when absent."""
    if "joint_std" not in (rec.dtype.names or ()):
        return None
    if count_of(msg, "joint_std") != j:
        raise WireError(
            topic, "joint_std", f"count {count_of(msg, 'joint_std')}, expected J={j}", "bad_count"
        )
    std = field_of(rec, "joint_std")
    check_finite(topic, "joint_std", std, "person", allow_nan=True)
    if (std < 0).any():
        raise WireError(topic, "joint_std", "negative standard deviation", "bad_value")
    return std.reshape(len(rec), j).astype(np.float64)


def poses_to_msg(
    stamp_ns: int,
    frame_id: str,
    ids: np.ndarray,
    joints: np.ndarray,
    views: np.ndarray,
    scores: np.ndarray,
    joint_std: np.ndarray | None = None,
) -> Any:
    """poses_to_cloud as a rosbags sensor_msgs/PointCloud2 (for a bag writer)."""
    return to_rosbags(poses_to_cloud(stamp_ns, frame_id, ids, joints, views, scores, joint_std))
