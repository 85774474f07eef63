"""Triangulation node: /maem/clusters -> per-keypoint RANSAC triangulation -> tracked 3D poses.

    ros2 run maem_ros triangulation --ros-args --params-file config/sportcenter.yaml
    maem-triangulation --ros-args --params-file config/demo.yaml

Subscribes ``/maem/clusters`` (reliable); publishes ``/maem/poses`` (PointCloud2, one point per
person: id, joints (3J world m, NaN = missing), views, score; see maem_ros/wire) and ``/maem/skeletons``
(MarkerArray; built only while something subscribes to it: a viewer, a recorder). Joints are
converted from the clusters' convention (MHR70 from the SAM 3D Body frontends) to
``output_convention`` (default sportcenter_13). Ids are the clusters' track ids when
the association node tracks (``temporal: on``, clusters with a ``track`` field); otherwise they come
from core.tracking.tracks.Tracker on the converted joints (post-hoc, 3D proximity). A person whose
track is not confirmed yet has id 4294967295 in poses (dropped unless ``publish_tentative``) and no
markers. A stamp that steps back or far ahead is held until the next frames confirm the jump (then a
stamp going back resets the tracker) or refute it (then it is dropped as
``stale_stamp``/``future_stamp``). More than ``max_people`` clusters or member pixels beyond
``pixel_margin`` reject the frame; joints beyond ``world_extent`` become NaN (counted
``joints_beyond_world_extent``). With ``bone_tolerance`` a
tracked person's limb joint whose bone length leaves the track's recent median by more than that
fraction is NaN (core.tracking.bone_filter, counted ``joints_bone_implausible``). Every clusters message
already waiting is taken before any is processed: those that waited for the node longer than the
backlog bound (``max_backlog``, by default 4 frame periods; core.backlog) are skipped unless
newest, counted ``dropped/behind`` (``keep_every_set: true`` processes every one, for replays that
want every frame; /diagnostics ``behind``, ``behind/for_s``, ``backlog/*``).
"""

from __future__ import annotations

import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from maem_ros.core.backlog import BacklogParams
from maem_ros.core.limits import InputLimits, check_clusters, mask_far_joints
from maem_ros.core.paramspec import param, param_specs
from maem_ros.core.skeleton import CONVENTIONS, convert, get_convention
from maem_ros.core.sync import StampGuard
from maem_ros.core.tracking.bone_filter import BoneLengthFilter
from maem_ros.core.tracking.joint_filter import JointFilterParams, filter_and_score
from maem_ros.core.triangulation.ransac import TriangulationParams
from maem_ros.ros import wire
from maem_ros.ros.diagnostics import RejectErrors, Stopwatch
from maem_ros.ros.intake import QueuedArrival, subscribe_counted, take_pending
from maem_ros.ros.node import MaemNode
from maem_ros.ros.overload import NodeBacklog
from maem_ros.ros.params import NodeParams
from maem_ros.ros.qos import DATA_QOS, MARKER_QOS

NODE_NAME = "triangulation"


@dataclass
class TriangulationNodeParams(NodeParams):
    """The triangulation node's own parameters (the method's are core TriangulationParams)."""

    rig: str = param("", "rig YAML, camera-JSON folder or shipped rig name (config/rigs/)")
    clusters_topic: str = param("maem/clusters", "input topic (relative: follows __ns)")
    poses_topic: str = param("maem/poses", "output topic (PointCloud2; relative: follows __ns)")
    skeletons_topic: str = param("maem/skeletons", "output topic (MarkerArray; relative)")
    frame_id: str = param("world", "header.frame_id of poses and markers")
    output_convention: str = param("sportcenter_13", "joints published", choices=tuple(sorted(CONVENTIONS)))
    track_gate: float = param(
        0.5, "m, mean joint distance gate for track assignment", minimum=0.0, exclusive_minimum=True
    )
    track_min_hits: int = param(3, "frames before a track gets an id", minimum=1)
    track_timeout: float = param(1.0, "s, a track unseen this long dies", minimum=0.0, exclusive_minimum=True)
    publish_tentative: bool = param(True, "publish unconfirmed persons with id 4294967295")
    marker_lifetime: float = param(
        0.5,
        "s, shortest marker lifetime (also before the frame period is known)",
        minimum=0.0,
        exclusive_minimum=True,
    )
    marker_lifetime_periods: float = param(
        3.0,
        "marker lifetime in frame periods (median "
        "arrival interval of clusters, steady clock), "
        "so markers outlive slow replays",
        minimum=0.0,
    )
    max_people: int = param(50, "clusters per message; more: dropped", minimum=1)
    pixel_margin: float = param(1.0, "image sizes a member keypoint may lie outside the image", minimum=0.0)
    world_extent: float = param(
        200.0, "m, joints farther from the world origin become NaN", minimum=0.0, exclusive_minimum=True
    )
    bone_tolerance: float = param(
        0.0,
        "fraction: a tracked person's elbow, wrist, knee or ankle "
        "whose limb bone differs from the track's median length "
        "by more than this is published NaN (core.tracking.bone_filter; "
        "0 = off, the paper)",
        minimum=0.0,
    )
    jump_tolerance: float = param(
        1.0,
        "s, a stamp this far ahead (beyond the time since the "
        "previous message) or any step back is held until the next "
        "messages confirm the jump",
        minimum=0.0,
        exclusive_minimum=True,
    )


PARAMS = param_specs(TriangulationNodeParams, BacklogParams, TriangulationParams, JointFilterParams)


#: heap touched at start (MiB): clusters messages and the RANSAC arrays of a frame set
HEAP_PREFAULT_MB = 64


class TriangulationNode(MaemNode):
    """clusters -> triangulate -> convert -> track -> poses + skeleton markers."""

    NAME, PARAMS, HEAP_PREFAULT_MB = NODE_NAME, PARAMS, HEAP_PREFAULT_MB

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        p = self.p
        self.rig = self.load_rig()
        from maem_ros.core.tracking.tracks import Tracker
        from maem_ros.core.triangulation import ransac_kernel as triangulation_kernel
        from maem_ros.core.triangulation.ransac import triangulate_members
        from maem_ros.core.triangulation.ransac_kernel import use_numba

        with self.config_errors():
            self.params = TriangulationParams.from_mapping(p)
            self.tracker = Tracker(
                gate_m=p["track_gate"], min_hits=p["track_min_hits"], timeout_s=p["track_timeout"]
            )
            self.limits = InputLimits(
                max_people=p["max_people"], pixel_margin=p["pixel_margin"], world_extent_m=p["world_extent"]
            )
            self.guard = StampGuard(int(round(p["jump_tolerance"] * 1e9)))
            self.joint_filter = JointFilterParams.from_mapping(p).make()
            self.bone_filter = (
                BoneLengthFilter(get_convention(p["output_convention"]).names, p["bone_tolerance"])
                if p["bone_tolerance"] > 0
                else None
            )
            if use_numba(self.params.ransac_backend):
                triangulation_kernel.warmup()  # load/compile the kernel now, not on frame 1
        self._triangulate = triangulate_members
        self._P = np.stack([c.P for c in self.rig.cameras])
        self.output = get_convention(p["output_convention"])
        self.frame_id = p["frame_id"]
        self.publish_tentative = p["publish_tentative"]
        self.marker_lifetime = p["marker_lifetime"]
        self.marker_lifetime_periods = p["marker_lifetime_periods"]
        self._arrivals: deque[float] = deque(maxlen=16)
        self.start_diagnostics()
        self.backlog = NodeBacklog(self, self.diag, BacklogParams.from_mapping(p), "clusters message(s)")
        self._arrived: list[tuple[PointCloud2, int]] = []  # taken, not decided on yet
        self._taking = False
        self.pose_pub = self.create_publisher(PointCloud2, p["poses_topic"], DATA_QOS)
        self.marker_pub = self.create_publisher(MarkerArray, p["skeletons_topic"], MARKER_QOS)
        self.topic = self.resolve_topic_name(p["clusters_topic"])
        self._arrival = QueuedArrival()  # arrival times that see every queue on the way
        self.sub = subscribe_counted(
            self, self.diag, PointCloud2, self.topic, self.on_clusters, DATA_QOS, with_info=True
        )
        self.get_logger().info(
            f"{self.topic} -> {self.pose_pub.topic_name}, {self.marker_pub.topic_name} ({self.output.name})"
        )

    def convert(self, joints: np.ndarray) -> np.ndarray:
        """(P,J,3) joints in the clusters' convention -> (P,J_out,3) in output_convention."""
        return convert(joints, self.output)

    def lifetime_s(self) -> float:
        """Marker lifetime: marker_lifetime_periods x the median arrival interval of the last
        clusters messages (steady clock), at least marker_lifetime."""
        if len(self._arrivals) < 2:
            return self.marker_lifetime
        period = float(np.median(np.diff(self._arrivals)))
        return max(self.marker_lifetime, self.marker_lifetime_periods * period)

    def on_clusters(self, msg: PointCloud2, info) -> None:
        """One clusters message: queue it; then (unless taking already) take every other one
        waiting in the DDS queue and decide on all of them together."""
        self._arrivals.append(time.monotonic())
        self._arrived.append(
            (msg, self._arrival.arrival_ns(self.topic, self.get_clock().now().nanoseconds, info))
        )
        if self._taking:
            return
        self._taking = True
        try:
            take_pending(self.sub)
        finally:
            self._taking = False
        batch, self._arrived = self._arrived, []
        self._decide([f for f in (self._decode(m, ready) for m, ready in batch) if f])

    def _decode(self, msg: PointCloud2, ready_ns: int) -> tuple[wire.ClusterFrame, int] | None:
        """(frame, ready time) of one message, None (counted) when it is bad."""
        with RejectErrors(self.diag, self.topic, "bad_clusters") as step:
            with Stopwatch(self.diag, "decode"):
                cf = wire.msg_to_clusters(msg, self.topic, len(self.rig))
                check_clusters(
                    len(np.unique(cf.cluster)),
                    cf.camera,
                    cf.kpts2d,
                    self.rig,
                    self.limits,
                    f"{self.topic} {cf.stamp_ns}",
                )
        return None if step.failed else (cf, ready_ns)

    def _decide(self, frames: list[tuple[wire.ClusterFrame, int]]) -> None:
        """Stamp guard, then the overload policy, then process what is left in order."""
        accepted = []
        for cf, ready in frames:
            verdict = self.guard.push(cf.stamp_ns, (cf, ready), self.get_clock().now().nanoseconds)
            for reason, (bad, _) in verdict.dropped:
                self.diag.reject(
                    reason,
                    f"{self.topic}: stamp {bad.stamp_ns} does not continue "
                    f"the stream (last {self.guard.last}); frame ignored",
                )
            if verdict.jumped_back:
                self._reset_tracks(verdict.accepted[0][0])
            accepted += [item for _, item in verdict.accepted]
        if not accepted:
            return
        kept = self.backlog.select(accepted, [r for _, r in accepted], [cf.stamp_ns for cf, _ in accepted])
        for k, (cf, ready) in enumerate(kept):
            if self.backlog.still_fresh(ready, cf.stamp_ns, k < len(kept) - 1):
                self.process(cf)

    def _reset_tracks(self, stamp_ns: int) -> None:
        self.tracker.reset()
        if self.bone_filter is not None:
            self.bone_filter.reset()
        if self.joint_filter is not None:
            self.joint_filter.reset()
        self.diag.count("tracker_resets")
        self.diag.log_throttled(
            "tracker_reset",
            f"{self.topic}: stamps went back to "
            f"{stamp_ns} (confirmed by the next {self.guard.confirm} "
            f"frames); tracker reset",
        )

    def process(self, cf: wire.ClusterFrame) -> None:
        """Triangulate, convert, track and publish one clusters frame."""
        with RejectErrors(self.diag, self.topic, "triangulation_error") as step:
            with Stopwatch(self.diag, "triangulate"):
                poses = self._triangulate(self._P, *cf.dense(), self.params)
            joints = self.convert(
                np.asarray(poses.joints, dtype=np.float64).reshape(len(poses), cf.num_joints, 3)
            )
            cov = self.convert(
                np.asarray(poses.joint_cov, dtype=np.float64).reshape(len(poses), cf.num_joints, 9)
            )
            cov = cov.reshape(cov.shape[:2] + (3, 3))
            if poses.rejected is not None and poses.rejected.any():  # tau_member
                self.diag.count("members_rejected", int(poses.rejected.sum()))
            far = mask_far_joints(joints, self.limits)
            if far:
                self.diag.count("joints_beyond_world_extent", far)
        if step.failed:
            return
        with RejectErrors(self.diag, f"{self.topic} {cf.stamp_ns}", "publish_error") as step:
            with Stopwatch(self.diag, "track"):
                ids = cf.cluster_tracks()
                if ids is None:
                    ids = np.asarray(self.tracker.update(cf.stamp_ns, joints), dtype=np.int64)
                joints, std, scores = filter_and_score(
                    cf.stamp_ns,
                    ids,
                    joints,
                    cov,
                    np.asarray(poses.detection_scores),
                    self.joint_filter,
                    self.params.pose_score,
                    self.params.score_ref_m,
                )
                if self.bone_filter is not None:
                    implausible = self.bone_filter.apply(ids, joints)
                    if implausible:
                        self.diag.count("joints_bone_implausible", implausible)
            self.publish(cf.stamp_ns, ids, joints, np.asarray(poses.views), scores, std)
        if not step.failed:
            self.diag.ok()

    def publish(
        self,
        stamp_ns: int,
        ids: np.ndarray,
        joints: np.ndarray,
        views: np.ndarray,
        scores: np.ndarray,
        joint_std: np.ndarray,
    ) -> None:
        """Poses (with per-joint std, m) and skeleton markers of one frame set."""
        keep = np.ones(len(ids), bool) if self.publish_tentative else ids >= 0
        with Stopwatch(self.diag, "encode"):
            poses_msg = wire.poses_to_msg(
                stamp_ns, self.frame_id, ids[keep], joints[keep], views[keep], scores[keep], joint_std[keep]
            )
        # poses first: the markers (one Python object per point) must not delay them
        self.pose_pub.publish(poses_msg)
        # the markers cost about a third of this node's work per frame: made only for a subscriber
        # (the topic is volatile, so one that joins later misses nothing it could have had)
        if self.marker_pub.get_subscription_count() > 0:
            with Stopwatch(self.diag, "markers"):
                markers = wire.skeleton_markers(
                    stamp_ns, self.frame_id, ids, joints, self.output.bones, self.lifetime_s()
                )
            self.marker_pub.publish(markers)
        self.diag.set("last_persons", int(len(ids)))
        self.diag.set("last_tracked", int((ids >= 0).sum()))
        self.diag.set("last_stamp_ns", stamp_ns)


def main(args: list[str] | None = None) -> int:
    return TriangulationNode.main(args)


if __name__ == "__main__":
    sys.exit(main())
