"""Clusters (``/maem/clusters``): one point per (cluster, member view), with optional track
fields. No rclpy."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Rig
from maem_ros.wire.cdr import to_rosbags
from maem_ros.wire.cloud import (
    F32,
    U8,
    U16,
    U32,
    Cloud,
    WireError,
    check_finite,
    check_score,
    checked_stamp_ns,
    count_of,
    field_of,
    new_cloud,
    view_cloud,
)
from maem_ros.wire.poses import UNTRACKED_ID

CLUSTER_TYPES = {"cluster": U32, "camera": U16, "detection": U16, "score": F32, "cost": F32, "kpts2d": F32}
#: optional cluster fields, written with temporal association: ``track``(uint32 track id,
#: UNTRACKED_ID = tentative) ``track_flags``(uint8, core.tracking.temporal FLAG_* bits)
CLUSTER_TRACK_TYPES = {"track": U32, "track_flags": U8}


@dataclass
class ClusterFrame:
    """Decoded /maem/clusters: M member rows (cluster, camera index, detection, score, cost, kpts2d).

    kpts2d (M,J,2) rectified px; cost (M,) metres (NaN = member alone).
    """

    stamp_ns: int
    frame_id: str
    cluster: np.ndarray
    camera: np.ndarray
    detection: np.ndarray
    score: np.ndarray
    cost: np.ndarray
    kpts2d: np.ndarray
    track: np.ndarray | None = None  # (M,) int64 track id per row, -1 = tentative; None = untracked
    track_flags: np.ndarray | None = None  # (M,) uint8 core.tracking.temporal FLAG_* bits

    @property
    def num_joints(self) -> int:
        return int(self.kpts2d.shape[1])

    def dense(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Dense padded member arrays for core.triangulation.ransac.triangulate_members: cam (C,M),
        kpts2d (C,M,J,2), score (C,M), present (C,M); clusters in order of first row."""
        from maem_ros.core.triangulation.ransac import pad_members  # local: wire stays importable alone

        return pad_members(
            self.cluster,
            self.camera.astype(np.int64),
            self.kpts2d.astype(np.float64),
            self.score.astype(np.float64),
        )

    def cluster_tracks(self) -> np.ndarray | None:
        """(C,) track id per cluster in to_core order (-1 = tentative), None without tracks."""
        if self.track is None:
            return None
        _, first = np.unique(self.cluster, return_index=True)
        return self.track[np.sort(first)]


def clusters_to_cloud(
    stamp_ns: int,
    frame_id: str,
    rig: Rig,
    frames: Mapping[str, FrameDetections],
    clusters: Sequence,
    track_ids: Sequence[int] | np.ndarray | None = None,
    track_flags: Sequence[int] | np.ndarray | None = None,
) -> Cloud:
    """core Clusters (members = (camera index, detection index)) -> PointCloud2.

    ``frames`` are the FrameDetections the clusters index into, keyed by camera name; J is
    taken from them (0 points and J of any frame when there are no clusters). With
    ``track_ids`` (one per cluster, < 0 = tentative) the optional ``track`` and ``track_flags``
    fields are written too.
    """
    j = next((f.num_joints for f in frames.values()), 0)
    members, costs = [], []  # one row per (cluster, member); a member without a cost: no row
    for cl in clusters:
        m, c = np.asarray(cl.members, np.int64).reshape(-1, 2), np.asarray(cl.costs).reshape(-1)
        n = min(len(m), len(c))
        members.append(m[:n])
        costs.append(c[:n])
    per_row = np.repeat(np.arange(len(clusters)), [len(m) for m in members])
    fields = [
        ("cluster", U32, 1),
        ("camera", U16, 1),
        ("detection", U16, 1),
        ("score", F32, 1),
        ("cost", F32, 1),
        ("kpts2d", F32, 2 * j),
    ]
    if track_ids is not None:
        fields += [(name, dt, 1) for name, dt in CLUSTER_TRACK_TYPES.items()]
    msg, rec = new_cloud(stamp_ns, frame_id, fields, len(per_row))
    if not len(per_row):
        return msg
    if track_ids is not None:
        ids = np.asarray(track_ids, np.int64)[per_row]
        rec["track"] = np.where(ids < 0, UNTRACKED_ID, ids).astype(np.uint32)
        flags = np.zeros(len(clusters), np.uint8) if track_flags is None else track_flags
        rec["track_flags"] = np.asarray(flags, np.uint8)[per_row]
    cam_det = np.concatenate(members)
    rec["cluster"] = per_row
    rec["camera"] = cam_det[:, 0]
    rec["detection"] = cam_det[:, 1]
    rec["cost"] = np.concatenate(costs)
    names = rig.names
    for c in np.unique(cam_det[:, 0]):  # gathered per camera: rows index into its detections
        rows = cam_det[:, 0] == c
        f, d = frames[names[c]], cam_det[rows, 1]
        rec["score"][rows] = f.scores[d]
        rec["kpts2d"][rows] = f.kpts2d[d].reshape(len(d), -1)
    return msg


def msg_to_clusters(msg: Any, topic: str, num_cameras: int) -> ClusterFrame:
    """PointCloud2 -> ClusterFrame, validated (camera index < num_cameras, unique members)."""
    rec = view_cloud(msg, topic, CLUSTER_TYPES, CLUSTER_TRACK_TYPES)
    names = rec.dtype.names or ()
    tracked = "track" in names
    if tracked != ("track_flags" in names):
        raise WireError(
            topic,
            "track" if not tracked else "track_flags",
            "missing field (track and track_flags come together)",
            "missing_field",
        )
    for name in ("cluster", "camera", "detection", "score", "cost") + (
        tuple(CLUSTER_TRACK_TYPES) if tracked else ()
    ):
        if count_of(msg, name) != 1:
            raise WireError(topic, name, f"count {count_of(msg, name)}, expected 1", "bad_count")
    c2 = count_of(msg, "kpts2d")
    if c2 % 2 or c2 == 0:
        raise WireError(topic, "kpts2d", f"count {c2}, expected 2J (J >= 1)", "bad_count")
    n = len(rec)
    f = {name: field_of(rec, name) for name in CLUSTER_TYPES}
    camera = f["camera"][:, 0].astype(np.int64)
    if n and camera.max() >= num_cameras:
        raise WireError(
            topic,
            "camera",
            f"index {int(camera.max())} but the rig has {num_cameras} cameras",
            "unknown_camera",
        )
    pairs = camera * 65536 + f["detection"][:, 0]
    if len(np.unique(pairs)) != n:
        raise WireError(topic, "detection", "a (camera, detection) pair appears twice", "duplicate_member")
    check_finite(topic, "kpts2d", f["kpts2d"], "member", allow_nan=True)  # NaN = not seen
    check_finite(topic, "score", f["score"], "member")
    check_finite(topic, "cost", f["cost"], "member", allow_nan=True)
    check_score(topic, f["score"][:, 0], "member")
    track = flags = None
    if tracked:
        raw = field_of(rec, "track")[:, 0].astype(np.int64)
        track = np.where(raw == UNTRACKED_ID, -1, raw)
        flags = field_of(rec, "track_flags")[:, 0].astype(np.uint8)
        cluster = f["cluster"][:, 0].astype(np.int64)
        _, first, inverse = np.unique(cluster, return_index=True, return_inverse=True)
        if np.any(track != track[first][inverse]):
            raise WireError(topic, "track", "members of one cluster carry different track ids", "bad_track")
    return ClusterFrame(
        track=track,
        track_flags=flags,
        stamp_ns=checked_stamp_ns(msg.header.stamp, topic),
        frame_id=msg.header.frame_id,
        cluster=f["cluster"][:, 0].astype(np.int64),
        camera=camera,
        detection=f["detection"][:, 0].astype(np.int64),
        score=f["score"][:, 0].astype(np.float64),
        cost=f["cost"][:, 0].astype(np.float64),
        kpts2d=f["kpts2d"].reshape(n, c2 // 2, 2).astype(np.float64),
    )


def clusters_to_msg(
    stamp_ns: int,
    frame_id: str,
    rig: Rig,
    frames: Mapping[str, FrameDetections],
    clusters: Sequence,
    track_ids: Sequence[int] | np.ndarray | None = None,
    track_flags: Sequence[int] | np.ndarray | None = None,
) -> Any:
    """clusters_to_cloud as a rosbags sensor_msgs/PointCloud2 (for a bag writer)."""
    return to_rosbags(clusters_to_cloud(stamp_ns, frame_id, rig, frames, clusters, track_ids, track_flags))
