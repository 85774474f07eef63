"""maem-demo measures that need no ground truth: people per frame, reprojection error of the
triangulated joints in the views that saw them, bone-length stability over time.

All of them read what the graph recorded (/maem/poses, /maem/clusters), so a real capture
without ground truth (e.g. Pose2Sim Demo_MultiPerson through the mediapipe frontend) is
measured the same way as the simulator's bag.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.skeleton import KeypointConvention
from maem_ros.core.triangulation.ransac import TriangulationParams, mirror_permutation, triangulate_members
from maem_ros.wire import UNTRACKED_ID, msg_to_clusters

CLUSTERS_TOPIC = "/maem/clusters"
REPROJECTION_DEFINITION = (
    "reprojection error = distance (rectified px) between a triangulated joint projected into a "
    "member view of its cluster and that view's 2D keypoint, over every (joint, view) with both "
    "finite (a landmark the frontend marked missing, e.g. mediapipe's visibility under "
    "min_visibility, is NaN and takes no part); the clusters are the recorded /maem/clusters, "
    "triangulated again with the triangulation node's parameters (the same core function, so the "
    "same joints; a view relabelled left/right by left_right is compared with its relabelled "
    "keypoints). reprojection_px_mean averages every such pair over the members the "
    "triangulation kept; members it left out as a whole (tau_member: median error over the "
    "person's joints >= tau_member px, e.g. a body mixed from two people) are counted in "
    "reprojection_members_rejected and included only in reprojection_px_mean_all_members; "
    "_inliers averages only pairs under tau_kps (the views the per-keypoint RANSAC used)"
)
#: bones whose length is checked over time (both sides), by joint name
STABLE_BONES = (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle"))
#: a track needs this many frames with the bone for its length CV to count
MIN_TRACK_FRAMES = 10


def people_per_frame(stamps: Sequence[int], poses: Mapping[int, Any]) -> list[int]:
    """Per played stamp, the people published on /maem/poses (0 when none arrived)."""
    out = []
    for s in stamps:
        pf = poses.get(s)
        out.append(0 if pf is None else int(np.isfinite(pf.joints).all(-1).any(-1).sum()))
    return out


def reprojection_errors(
    record: Path, rig: Rig, params: TriangulationParams, stamps: Sequence[int]
) -> MemberErrors:
    """Every finite (joint, member view) reprojection error (px) of the recorded clusters."""
    errs = MemberErrors()
    if not (record / "metadata.yaml").is_file():
        return errs
    wanted = set(stamps)
    P_rig = np.stack([c.P for c in rig])
    for m in bagio.read_messages(record, [CLUSTERS_TOPIC]):
        cf = msg_to_clusters(m.decode(), m.topic, len(rig))
        if cf.stamp_ns not in wanted or not len(cf.cluster):
            continue
        wanted.discard(cf.stamp_ns)  # first message per stamp, as the poses
        errs.add(member_reprojection_errors(P_rig, *cf.dense(), params)[1])
    return errs


@dataclass
class MemberErrors:
    """Reprojection errors (px) collected over frames: of the members the triangulation kept,
    of the members it rejected as a whole (tau_member), and the member counts."""

    kept: list[np.ndarray] = field(default_factory=list)
    rejected: list[np.ndarray] = field(default_factory=list)
    members: int = 0
    members_rejected: int = 0

    def add(self, other: MemberErrors) -> None:
        self.kept += other.kept
        self.rejected += other.rejected
        self.members += other.members
        self.members_rejected += other.members_rejected

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        cat = lambda a: np.concatenate(a) if a else np.zeros(0)  # noqa: E731
        return cat(self.kept), cat(self.rejected)


def member_reprojection_errors(
    P_rig: np.ndarray,
    cam: np.ndarray,
    uv: np.ndarray,
    score: np.ndarray,
    present: np.ndarray,
    params: TriangulationParams,
) -> tuple[Any, MemberErrors]:
    """Triangulate dense member arrays (core.triangulation.ransac.pad_members) and measure: (Poses,
    px errors of every finite joint in every member view, split by kept / rejected member)."""
    poses = triangulate_members(P_rig, cam, uv, score, present, params)
    if poses.mirrored is not None:  # views relabelled left/right are compared as such
        uv = np.where(poses.mirrored[:, :, None, None], uv[:, :, mirror_permutation(uv.shape[2])], uv)
    X = np.asarray(poses.joints)  # (C,J,3)
    Xh = np.concatenate([X, np.ones(X.shape[:2] + (1,))], axis=-1)
    proj = np.einsum("cmij,ckj->cmki", P_rig[cam], Xh)  # (C,M,J,3)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(proj[..., :2] / proj[..., 2:] - uv, axis=-1)  # (C,M,J)
    valid = np.isfinite(e) & (proj[..., 2] > 0)
    rejected = poses.rejected if poses.rejected is not None else np.zeros(present.shape, bool)
    kept = present & ~rejected
    return poses, MemberErrors(
        [e[kept[:, :, None] & valid]],
        [e[rejected[:, :, None] & valid]],
        int(present.sum()),
        int(rejected.sum()),
    )


def reprojection_summary(errors: MemberErrors, tau_kps: float) -> dict[str, float | int | None]:
    """report.json's reprojection entries (see REPROJECTION_DEFINITION)."""
    kept, rejected = errors.arrays()
    inl = kept[kept < tau_kps]
    every = np.concatenate([kept, rejected])
    mean = lambda a: float(a.mean()) if a.size else None  # noqa: E731
    return {
        "reprojection_px_mean": mean(kept),
        "reprojection_px_median": float(np.median(kept)) if kept.size else None,
        "reprojection_px_mean_inliers": mean(inl),
        "reprojection_inlier_fraction": float(inl.size / kept.size) if kept.size else None,
        "reprojection_pairs": int(kept.size),
        "reprojection_px_mean_all_members": mean(every),
        "reprojection_members": errors.members,
        "reprojection_members_rejected": errors.members_rejected,
    }


def joints_found(poses: Mapping[int, Any], convention: KeypointConvention) -> dict[str, Any]:
    """Per joint name, the fraction of published people (every frame) with that joint finite."""
    rows = [pf.joints for pf in poses.values() if len(pf.joints)]
    if not rows:
        return {"joints_found": {}, "joints_found_mean": None}
    found = np.isfinite(np.concatenate(rows)).all(-1).mean(0)
    return {
        "joints_found": {n: float(f) for n, f in zip(convention.names, found)},
        "joints_found_mean": float(found.mean()),
    }


def bone_length_cv(
    poses: Mapping[int, Any], convention: KeypointConvention, min_frames: int = MIN_TRACK_FRAMES
) -> dict[str, Any]:
    """Coefficient of variation (std / mean) of each stable bone's length over each track's
    frames, per bone name the mean over tracks with >= ``min_frames`` frames, and the worst."""
    idx = {n: i for i, n in enumerate(convention.names)}
    bones = [
        (f"{s}_{a}", f"{s}_{b}")
        for s in ("left", "right")
        for a, b in STABLE_BONES
        if f"{s}_{a}" in idx and f"{s}_{b}" in idx
    ]
    tracks: dict[int, list[np.ndarray]] = {}
    for pf in poses.values():
        for pid, joints in zip(pf.ids, pf.joints):
            if int(pid) != UNTRACKED_ID:
                tracks.setdefault(int(pid), []).append(joints)
    per_bone: dict[str, list[float]] = {}
    for seq in tracks.values():
        J = np.stack(seq)
        for a, b in bones:
            length = np.linalg.norm(J[:, idx[a]] - J[:, idx[b]], axis=-1)
            length = length[np.isfinite(length)]
            if length.size >= min_frames and length.mean() > 0:
                per_bone.setdefault(f"{a}-{b}", []).append(float(length.std() / length.mean()))
    cv = {bone: float(np.mean(v)) for bone, v in per_bone.items()}
    return {
        "bone_length_cv": cv,
        "bone_length_cv_max": max(cv.values()) if cv else None,
        "bone_length_cv_mean": float(np.mean(list(cv.values()))) if cv else None,
        "bone_length_tracks": sum(1 for seq in tracks.values() if len(seq) >= min_frames),
    }
