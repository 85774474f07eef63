"""Association node: every camera's detections -> synchronised frame sets -> MAEM clusters.

    ros2 run maem_ros association --ros-args --params-file config/sportcenter.yaml
    maem-association --ros-args --params-file config/demo.yaml

Subscribes ``<camera>/detections`` for each rig camera (reliable, keep last 10; taken serialized,
into an array without rclpy's bytes copy (ros.raw_take), and decoded in place, wire.cdr_to_cloud:
rclpy's own deserialisation of a 1.8 MB full-mesh message costs more than its association; each
message checked whole on receipt, f32 vertices in the pair gates' preparing pass,
:func:`checked_detections`), takes every pending message of all cameras before the
synchroniser decides (a busy executor would run the poll timer first and leave messages of the
frame in the DDS queues) and counts ``max_wait`` and lags from each message's rmw receive time,
groups them by capture time (stamp + the rig camera's ``time_offset``; the published frame set is
stamped with the reference's capture time) with core.sync.ApproximateTimeSync (``slop``,
``max_wait``, ``min_cameras``; while
a message waits in it a timer polls every ``poll_period`` so a silent camera never stalls the
graph; a camera lagging beyond
``max_wait`` is not waited for (``max_lag`` compensates a known lag); one camera's stale/future
stamps are dropped for that camera, a jump of most cameras or of /clock resets the queues; every
dropped message is counted as ``dropped/sync_<reason>``; more than ``max_detections`` per message
or pixels beyond ``pixel_margin`` are rejected; a node that fell behind skips the frame sets that
waited for it longer than the backlog bound, counted ``dropped/behind``: ``max_backlog`` s, by
default 4 frame periods (core.backlog; ``keep_every_set: true`` processes every set, for
replays that want every frame; /diagnostics ``behind``, ``behind/for_s``, ``backlog/*``;
a set that waited a frame period, or any set while the node's ``load`` is above ``light_load``,
runs the track stage's light step: ``light_when_late``),
runs core.tracking.temporal.TemporalAssociator (``temporal: on``, default: detections explained by the
tracks' predictions first, core.association.pipeline.associate on the rest; clusters carry track ids) or
core.association.pipeline.associate alone (``temporal: off``, the per-frame paper pipeline) with the paper's
thresholds and publishes ``/maem/clusters`` (PointCloud2, one point per (cluster, member view), see
maem_ros/wire; an empty cloud for a frame set without clusters, so downstream still sees every frame).
A stamp going backwards or jumping forward by more than ``max_gap_s`` ends all tracks.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from rclpy.clock import ClockChange, JumpThreshold
from rclpy.duration import Duration
from sensor_msgs.msg import PointCloud2

from maem_ros.core.association import AssociationParams, ExecutionParams
from maem_ros.core.association import warmup as warmup_association
from maem_ros.core.association.gates import PairGates
from maem_ros.core.backlog import BacklogParams, LoadMeter
from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry import Rig
from maem_ros.core.limits import InputLimits, check_detection_arrays
from maem_ros.core.paramspec import param, param_specs
from maem_ros.core.sync import ApproximateTimeSync, SyncStats
from maem_ros.core.tracking.temporal import TemporalParams
from maem_ros.ros import wire
from maem_ros.ros.diagnostics import RejectErrors, Stopwatch
from maem_ros.ros.intake import QueuedArrival, subscribe_counted, take_pending
from maem_ros.ros.node import MaemNode
from maem_ros.ros.overload import NodeBacklog
from maem_ros.ros.params import ConfigError, NodeParams
from maem_ros.ros.qos import DATA_DEPTH, DATA_QOS, data_qos
from maem_ros.ros.rig_tf import publish_rig_tf

NODE_NAME = "association"

#: core.association.pipeline.AssociationResult.stats keys reported as cumulative counts in /diagnostics
GATE_COUNTS = (
    "pairs_considered",
    "rejected_score",
    "rejected_reproj",
    "rejected_epipolar",
    "matched_pairs",
    "conflicts_removed",
    "clusters_below_k_min",
)
#: ... and as per-stage times (stats key -> /diagnostics stage, ms)
STAGE_TIMES = {
    "t_reproj_ms": "reproj",
    "t_epipolar_ms": "epipolar",
    "t_cost_ms": "cost",
    "t_match_ms": "match",
    "t_cluster_ms": "cluster",
}

RIG_DESCRIPTION = "rig YAML, camera-JSON folder or shipped rig name (config/rigs/)"


@dataclass
class AssociationNodeParams(NodeParams):
    """The association node's own parameters (the method's are core AssociationParams, how it
    runs core ExecutionParams)."""

    rig: str = param("", RIG_DESCRIPTION)
    cameras: list = param([], "cameras to subscribe (default: every rig camera)")
    frame_id: str = param("world", "header.frame_id of /maem/clusters (the rig's world frame)")
    clusters_topic: str = param("maem/clusters", "output topic (relative: follows __ns)")
    slop: float = param(0.02, "s, stamps within this of the reference belong to one frame set", minimum=0.0)
    max_wait: float = param(
        0.15, "s, emit a partial frame set after waiting this long", minimum=0.0, exclusive_minimum=True
    )
    min_cameras: int = param(2, "cameras needed for a partial frame set", minimum=2)
    queue_size: int = param(
        DATA_DEPTH,
        "messages per camera held (DDS reader history and "
        "synchroniser queue): a stall this many frames long "
        "loses nothing",
        minimum=1,
    )
    poll_period: float = param(0.01, "s, synchroniser poll timer", minimum=0.0, exclusive_minimum=True)
    max_lag: float = param(
        0.0,
        "s, wait up to this lag (+ max_wait) for a camera that lags the "
        "others (0 = a camera lagging beyond max_wait is not waited for)",
        minimum=0.0,
    )
    jump_tolerance: float = param(
        1.0,
        "s, a stamp this far from the other cameras' is a jump (held; a reset when most cameras jump)",
        minimum=0.0,
        exclusive_minimum=True,
    )
    reset_on_clock_jump: bool = param(
        True, "with use_sim_time: reset the synchroniser when /clock jumps back"
    )
    max_detections: int = param(100, "detections per camera message; more: dropped", minimum=1)
    pixel_margin: float = param(1.0, "image sizes a pixel coordinate may lie outside the image", minimum=0.0)
    publish_tf: bool = param(
        True, "publish world -> each rig camera on /tf_static (transient local) at start"
    )
    light_when_late: bool = param(
        True,
        "a frame set that waited more than a frame period for the node (it is falling behind) "
        "runs the track stage's light step (track members verified on 2D keypoints, no refine "
        "pass, new people only every light_new_every s; counted light_steps, new_deferred); "
        "false = every set the full step",
    )
    light_load: float = param(
        0.8,
        "with light_when_late: the light step also runs while the node's load (the share of "
        "the last 0.25 s its callbacks took, /diagnostics load) is above this, before any set "
        "has waited; 1 = only sets that waited",
        minimum=0.0,
        maximum=1.0,
    )


PARAMS = param_specs(AssociationNodeParams, BacklogParams, AssociationParams, ExecutionParams, TemporalParams)
#: core.tracking.temporal stats reported as cumulative counts in /diagnostics
TRACK_COUNTS = (
    "tracks_started",
    "tracks_reacquired",
    "tracks_merged",
    "tracks_ended",
    "tracks_few_views",
    "tracks_one_view",
    "track_resets",
    "verify_dropped",
    "light_steps",
    "new_deferred",
)


#: frames of the start-up warm pass (AssociationNode._warm_path): the first without tracks, then
#: the track-assisted full step, then its light step
WARM_FRAMES = 3

#: heap touched at start (MiB): six cameras' full-mesh messages in flight (rmw buffer + bytes,
#: ~1.8 MB each) and one association step's arrays; measured: no page fault per message with it
HEAP_PREFAULT_MB = 192


class AssociationNode(MaemNode):
    """detections of N cameras -> ApproximateTimeSync -> associate -> /maem/clusters."""

    NAME, PARAMS, HEAP_PREFAULT_MB = NODE_NAME, PARAMS, HEAP_PREFAULT_MB

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        p = self.p
        self.rig = self.load_rig()
        cams = p["cameras"] or self.rig.names
        unknown = [c for c in cams if c not in self.rig]
        if unknown:
            raise ConfigError(f"parameter 'cameras': {unknown} not in rig {p['rig']!r} ({self.rig.names})")
        if p["min_cameras"] > len(cams):
            raise ConfigError(f"parameter 'min_cameras': {p['min_cameras']} > {len(cams)} cameras")
        from maem_ros.core.tracking.temporal import TemporalAssociator

        with self.config_errors():
            self.params = AssociationParams.from_mapping(p)
            self.temporal = TemporalAssociator(self.rig, self.params, TemporalParams.from_mapping(p))
        # compile/load the numba kernels now, not on the first frame
        warmup_association(self.params.execution.backend, self.params.epipolar_gate)
        # camera frames are prepared for the pair gates by checked_detections / prepared_detections
        self.gates = self.temporal.gates
        wire.warm_cdr_decoder()
        self.cameras = list(cams)
        self.frame_id = p["frame_id"]
        with self.config_errors():
            self.sync = ApproximateTimeSync(
                self.cameras,
                int(round(p["slop"] * 1e9)),
                int(round(p["max_wait"] * 1e9)),
                p["min_cameras"],
                queue_size=p["queue_size"],
                max_lag_ns=int(round(p["max_lag"] * 1e9)),
                jump_ns=int(round(p["jump_tolerance"] * 1e9)),
                time_offsets={c: self.rig[c].time_offset for c in self.cameras},
            )
            self.limits = InputLimits(max_detections=p["max_detections"], pixel_margin=p["pixel_margin"])
        self.warm_sets = self._warm_path()  # before the subscriptions: the first real set runs warm
        self._sync_seen = SyncStats()
        self._arrival = QueuedArrival()  # arrival times that see every queue on the way
        self.start_diagnostics()
        self.backlog = NodeBacklog(self, self.diag, BacklogParams.from_mapping(p), "frame set(s)")
        self._skip_stale = not p["keep_every_set"]
        self._light_when_late = p["light_when_late"]
        self._light_load = p["light_load"]
        self.load = LoadMeter()  # the callbacks' share of wall time (monotonic clock)
        self.pub = self.create_publisher(PointCloud2, p["clusters_topic"], DATA_QOS)
        self.subs = []
        self._ready: list = []  # complete sets not handled yet (in stamp order)
        # keep_every_set: the next set's turn after the executor's other ready work
        self._resume = self.create_guard_condition(self.on_timer)
        # inside _take_all: a message callback only receives (complete sets are handled
        # between rounds there, timeouts decided after it)
        self._taking = False
        detections_qos = data_qos(p["queue_size"])
        for cam in self.cameras:
            topic = self.resolve_topic_name(f"{cam}/detections")
            self.subs.append(
                subscribe_counted(
                    self,
                    self.diag,
                    PointCloud2,
                    topic,
                    partial(self.on_detections, cam, topic),
                    detections_qos,
                    raw=True,
                    with_info=True,
                    into_array=True,  # decoded in place: the frames keep views of it
                )
            )
        self.timer = self.create_timer(p["poll_period"], self.on_timer)
        self.tf_pub = publish_rig_tf(self, self.rig, self.frame_id) if p["publish_tf"] else None
        if p["reset_on_clock_jump"]:
            self._jump_handle = self.get_clock().create_jump_callback(
                JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=False),
                post_callback=self.on_clock_jump,
            )
        self.get_logger().info(f"{len(self.cameras)} cameras {self.cameras} -> {self.pub.topic_name}")

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _warm_path(self) -> int:
        """Run this node's path (check -> decode -> track-assisted association, its full and
        its light step -> encode) on simulated frame sets of its rig
        (core.synthetic.warm_sequence: WARM_FRAMES frames, the last one light), both wire
        layouts, with a throwaway track stage, so the first real frame set pays no first-call costs (lazy
        imports, kernel dispatch, first allocations): a fresh track stage's first set cost about
        seven times a warm one's, and at 60 fps a stream's first frames came late and some were
        skipped. A failure (a rig the generator cannot place people in) costs only the warm-up.
        Returns the frame sets run (0: skipped, logged)."""
        from rclpy.serialization import serialize_message

        from maem_ros.core.synthetic import warm_sequence
        from maem_ros.core.tracking.temporal import TemporalAssociator

        runs = 0
        try:
            sequence = warm_sequence(self.rig, frames=WARM_FRAMES)
            for layout in wire.WIRE_VERTICES:  # vertices and keypoints: every decoder runs once
                stage = TemporalAssociator(self.rig, self.params, self.temporal.tp)
                for k, frame_set in enumerate(sequence):
                    msgs = {c: wire.detections_to_msg(d, layout, layout) for c, d in frame_set.frames.items()}
                    # as the executors deliver them: bytes (rclpy's own take) for the first set,
                    # which decodes every vertex, writable arrays (ros.raw_take, the default) for
                    # the rest; a kernel compiled for read-only fields only would load its
                    # writable variant on the first real frame set
                    sent = {c: _as_received(serialize_message(m), k > 0) for c, m in msgs.items()}
                    self._warm_frame_set(stage, sent, light=k == len(sequence) - 1)
                    runs += 1
        except Exception as e:  # noqa: BLE001 - the warm-up must never keep the node from starting
            self.get_logger().warning(f"start-up warm-up skipped ({e}); the first frames run cold")
            return 0
        return runs

    def _warm_frame_set(self, stage: Any, sent: dict[str, bytes | np.ndarray], light: bool) -> None:
        """One serialized frame set (camera -> message) through the node's path with ``stage``."""
        checked = {
            cam: checked_detections(
                wire.cdr_to_cloud(data, f"/{cam}/detections"),
                "warm-up",
                cam,
                self.rig,
                self.limits,
                stage.gates,
            )
            for cam, data in sent.items()
            if cam in self.cameras
        }
        stamp = next(iter(checked.values())).stamp_ns
        vertices = stage.associates_new(stamp, light)
        items = {cam: prepared_detections(item, stage.gates, vertices) for cam, item in checked.items()}
        res = stage.step(items, stamp, light)
        wire.clusters_to_msg(stamp, self.frame_id, self.rig, items, res.clusters, res.track_ids, res.flags)

    def on_detections(self, cam: str, topic: str, data: bytes | np.ndarray, info) -> None:
        """One serialized detections message: check and queue it; then (unless called from
        _decide) take every other pending message and let the synchroniser decide."""
        if self._taking:  # inside _take_all: receive only
            self._receive(cam, topic, data, info)
            return
        with self._in_callback():
            self._receive(cam, topic, data, info)
            self._decide()

    @contextmanager
    def _in_callback(self) -> Iterator[None]:
        """Count the time inside in the node's load (the light step's trigger, /diagnostics)."""
        self.load.begin(time.monotonic_ns())
        try:
            yield
        finally:
            self.load.end(time.monotonic_ns())

    def _receive(self, cam: str, topic: str, data: bytes | np.ndarray, info) -> None:
        """Check one serialized message and queue it by its stamp: every field and limit is
        checked here (a bad message never takes a place in a frame set; counted with its
        reason), see :func:`checked_detections`."""
        with RejectErrors(self.diag, topic, "bad_detections") as step:
            with Stopwatch(self.diag, "check"):
                item = checked_detections(
                    wire.cdr_to_cloud(data, topic), topic, cam, self.rig, self.limits, self.gates
                )
        if step.failed:
            return
        now = self._now_ns()
        arrived = self._arrival.arrival_ns(topic, now, info)
        self._ready += self.sync.add(cam, item.stamp_ns, item, now, arrived, poll=False)
        if self.timer.is_canceled() and self.sync.pending():
            self.timer.reset()  # a set is waiting: poll it (max_wait) until it goes out

    def _decoded(self, fs, vertices: bool) -> dict[str, FrameDetections]:
        """The frame set's checked messages decoded and prepared for the pair gates (without
        the q4 mesh vertices when ``vertices`` is False: a step that reads none)."""
        with Stopwatch(self.diag, "decode"):
            return {cam: prepared_detections(item, self.gates, vertices) for cam, item in fs.items.items()}

    def _decide(self) -> None:
        """Take every message already waiting in the DDS queues (the executor runs the poll
        timer before them and takes one per subscription and wait; complete frame sets are
        handled as they complete), then poll: a frame set is declared partial only when its
        missing camera's message has not reached this process within max_wait of the
        reference's arrival (rmw receive time), never because the node was busy. Waiting
        messages also stop being overwritten in the keep-last history. When messages were
        left waiting (see _take_all) only complete sets go out now; the next callback, right
        away, decides the rest."""
        drained = self._take_all()
        ready, self._ready = self._ready, []
        ready += self.sync.poll(self._now_ns(), complete_only=not drained)
        if not self.sync.pending():
            # nothing waits for max_wait: a poll would find nothing (each executor wake-up
            # costs CPU); _receive re-arms the timer with the next queued message
            self.timer.cancel()
        self._emit(ready)

    def _emit(self, ready: list) -> None:
        """Handle frame sets ready together, the ones that waited beyond the backlog bound
        skipped (the newest never). With every set kept, one set per callback: the rest waits
        in ``_ready`` for the guard condition's callback, which comes after the executor's
        other ready work (a triangulation node in the same process takes its input between
        sets instead of seeing its history overflow behind a long backlog)."""
        if len(ready) > 1 and not self._skip_stale:
            ready, self._ready = ready[:1], ready[1:] + self._ready
            self._resume.trigger()
        if ready:
            ready = self.backlog.select(ready, [fs.ready_ns for fs in ready], [fs.stamp_ns for fs in ready])
        self._handle(ready)

    def _take_all(self) -> bool:
        """Receive every message waiting in the DDS queues, one per camera per round: the
        cameras' messages come in stamp order together, so after a stall (every camera's
        backlog waiting) each frame set completes, and is handled, as soon as its messages
        are in, instead of after all of the backlog was received. When stale sets are skipped
        (the default) the backlog is received first, which set is the newest is known only
        then, in at most ``queue_size`` rounds (what the DDS histories hold when this starts):
        messages that keep arriving faster than they are taken never keep the node from
        deciding. With every set kept, taking stops at the first complete set (one set per
        callback, see _emit; the rest waits in the DDS queues). Whether nothing was left
        waiting."""
        self._taking = True
        try:
            rounds = 0
            while self._take_round():
                if not self._skip_stale:
                    self._ready += self.sync.poll(self._now_ns(), complete_only=True)
                    if self._ready:
                        return False
                    continue
                rounds += 1
                if rounds >= self.sync.queue_size:
                    return False
            return True
        finally:
            self._taking = False

    def _receive_round(self) -> None:
        """One round of taking, receive only (the sets it completes wait in ``_ready`` for
        the next decision): a callback must not decide while the node works on sets."""
        taking, self._taking = self._taking, True
        try:
            self._take_round()
        finally:
            self._taking = taking

    def _take_round(self) -> int:
        """Receive (check and queue) at most one waiting message per camera; how many."""
        return sum(take_pending(sub, limit=1) for sub in self.subs)

    def on_timer(self) -> None:
        """The poll timer, and the guard condition of keep_every_set's next set."""
        with self._in_callback():
            self._decide()

    def on_clock_jump(self, jump) -> None:
        """/clock went back (use_sim_time, bag replayed again): start over, counted once."""
        if jump.clock_change == ClockChange.ROS_TIME_NO_CHANGE and jump.delta.nanoseconds < 0:
            self.sync.reset()
            self.get_logger().warning(
                f"clock jumped by {jump.delta.nanoseconds / 1e9:.3f} s: synchroniser reset"
            )
            self._sync_counters()

    def _handle(self, sets) -> None:
        self._sync_counters()
        for k, fs in enumerate(sets):
            # a set that went stale while the ones ahead of it were processed is skipped too
            if self.backlog.still_fresh(fs.ready_ns, fs.stamp_ns, k < len(sets) - 1):
                self.process(fs)
            if len(sets) > 1:  # a backlog: keep the DDS history from overwriting what arrived
                self._receive_round()

    def _sync_counters(self) -> None:
        """Report the synchroniser's drops (``sync_<reason>``), resets and state changes."""
        stats, seen = self.sync.stats, self._sync_seen
        for reason, total in stats.dropped.items():
            new = total - seen.dropped[reason]
            if new > 0:
                self.diag.reject(
                    f"sync_{reason.value}", f"synchroniser: {reason.value} +{new} (total {total})", n=new
                )
        for name in ("sets", "partial_sets", "timeouts", "resets"):
            new = getattr(stats, name) - getattr(seen, name)
            if new > 0:
                self.diag.count(f"sync_{name}", new)
        self._sync_seen = SyncStats(
            sets=stats.sets,
            partial_sets=stats.partial_sets,
            timeouts=stats.timeouts,
            resets=stats.resets,
            dropped=stats.dropped.copy(),
        )
        for event in self.sync.take_events():  # state changes: one line each, not per frame
            if event.kind == "rejoined":
                self.get_logger().info(event.text)
            else:
                self.get_logger().warning(event.text)
        self.diag.set(
            "lagging_cameras", ",".join(f"{c}:{lag * 1e3:.0f}ms" for c, lag in self.sync.lagging().items())
        )

    def _light_step(self, ready_ns: int) -> bool:
        """Whether a set ready at ``ready_ns`` (node clock) runs the light step: with
        light_when_late, when it waited more than a frame period (is_late) or the node's load
        is above light_load; never with keep_every_set (every set its full step)."""
        load = self.load.load(time.monotonic_ns())
        self.diag.set("load", round(load, 3))
        if not self._light_when_late or not self._skip_stale:
            return False
        return self.backlog.policy.is_late(ready_ns, self._now_ns()) or load > self._light_load

    def process(self, fs) -> None:
        """Associate one frame set and publish its clusters."""
        if fs.missing:
            self.diag.camera_missing(fs.missing)
            self.diag.set("missing_cameras_last", ",".join(fs.missing))
        else:
            self.diag.set("missing_cameras_last", "")
        # how long the set waited for this node after it was complete (time_ms/waited)
        self.diag.time("waited", (self._now_ns() - fs.ready_ns) / 1e6)
        with RejectErrors(self.diag, f"frame set {fs.stamp_ns}", "association_error") as step:
            light = self._light_step(fs.ready_ns)
            items = self._decoded(fs, self.temporal.associates_new(fs.stamp_ns, light))
            with Stopwatch(self.diag, "associate"):
                result = self.temporal.step(items, fs.stamp_ns, light)
            tracked = self.temporal.tp.temporal
            with Stopwatch(self.diag, "encode"):
                out = wire.clusters_to_msg(
                    fs.stamp_ns,
                    self.frame_id,
                    self.rig,
                    items,
                    result.clusters,
                    result.track_ids if tracked else None,
                    result.flags if tracked else None,
                )
        if step.failed:
            return
        self.pub.publish(out)
        self.diag.ok()
        self.diag.add_counts(result.stats, GATE_COUNTS)
        if tracked:
            self.diag.add_counts(result.stats, TRACK_COUNTS)
            if result.stats.get("track_resets"):
                self.get_logger().warning(
                    f"frame set {fs.stamp_ns}: stamp went back or jumped beyond max_gap_s; all tracks ended"
                )
            self.diag.set("last_tracks", int(result.stats["tracks"]))
            self.diag.set("last_tracks_confirmed", int(result.stats["tracks_confirmed"]))
        stages = {**STAGE_TIMES, "t_track_ms": "track"} if tracked else STAGE_TIMES
        for key, stage in stages.items():
            if key in result.stats:
                self.diag.time(stage, float(result.stats[key]))
        self.diag.set("last_clusters", len(result.clusters))
        self.diag.set("last_cameras", len(items))


def _as_received(data: bytes, into_array: bool) -> bytes | np.ndarray:
    """A serialized message as a subscription callback gets it: a writable uint8 array when
    taken into an array (ros.raw_take), else bytes."""
    return np.frombuffer(data, np.uint8).copy() if into_array else data


def checked_detections(
    cloud: Any, topic: str, cam: str, rig: Rig, limits: InputLimits, gates: PairGates
) -> FrameDetections | wire.DetectionsMessage:
    """One detections message read and checked whole, as the synchroniser queues it (WireError
    or InputError with the reason).

    f32 vertices that the pair gates prepare come back as the prepared FrameDetections: the
    gates' pass over the vertices is also their check, made here instead of the reader's, so a
    message costs one pass over its vertices, not one on reading and another when its frame
    set is processed, and a skipped set paid the same as before. Every other message comes back
    still encoded: q4 vertices are decoded (:func:`prepared_detections`) only for the frame
    sets processed, so a node that fell behind skips the stale ones without decoding them."""
    scan = bool(gates.prepare_strides())
    msg = wire.read_detections(cloud, topic, rig.names, expected_camera=cam, check_f32_vertices=not scan)
    item: FrameDetections | wire.DetectionsMessage = msg
    if not msg.vertices_checked:
        frame = msg.decode()
        found = gates.prepare_scanning(frame)
        msg = msg.check_vertices(topic) if found is None else msg.with_vertex_scan(topic, *found)
        item = frame.mark_validated()
    check_detection_arrays(cam, msg.bboxes, msg.kpts2d, msg.vertex_extremes, rig, limits, topic)
    return item


def prepared_detections(
    item: FrameDetections | wire.DetectionsMessage, gates: PairGates, vertices: bool = True
) -> FrameDetections:
    """A queued message (:func:`checked_detections`) decoded and prepared for the pair gates;
    ``vertices`` False: a q4 message without its mesh (decoded for a step that reads no vertex:
    TemporalAssociator.associates_new; f32 messages were prepared when they arrived)."""
    if isinstance(item, FrameDetections):
        return item
    return gates.prepare(item.decode()) if vertices else item.decode(vertices=False)


def main(args: list[str] | None = None) -> int:
    return AssociationNode.main(args)


if __name__ == "__main__":
    sys.exit(main())
