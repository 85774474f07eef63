"""Scaffolding shared by the tests that drive nodes from a test node: a node + executor on a
private rclpy Context, an in-process node graph spun in a thread (:class:`Graph`), recorders of
topics and /diagnostics, a detections player, the association + triangulation pipeline, the one
wait helper (:func:`wait_for`, on a condition or a Future), QoS profiles, and making sure a child
process never outlives its test. Fixtures (``graph``, ``scene``) are in conftest.py."""
from __future__ import annotations

import array
import subprocess
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numpy as np
import rclpy
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2, PointField
from visualization_msgs.msg import MarkerArray

from maem_ros.core.detections import FrameDetections
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.ros import wire
from maem_ros.ros.cli import shutdown_ros
from maem_ros.ros.fastdds import detach_discovery_listener
from maem_ros.ros.probe import DiagnosticsTable, fusion_links, unmatched_links
from maem_ros.ros.process import make_executor
from maem_ros.ros.qos import DATA_QOS

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@contextmanager
def ros_node(name: str) -> Iterator[tuple[rclpy.node.Node, SingleThreadedExecutor]]:
    """(node, executor) on a private Context; the test spins the executor itself."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(name, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.shutdown(timeout_sec=1.0)
        shutdown_ros(node, ctx)


def wait_for(cond: Callable[[], bool] | Future, timeout: float, on: Any = None,
             step: float = 0.02) -> bool:
    """Wait until ``cond()`` (or the Future ``cond`` is done), at most ``timeout`` s; its last
    value. ``on``: an executor to spin meanwhile, or a :class:`Graph` whose spinning thread is
    checked (an executor thread that died fails the test at once), or None (just wait)."""
    if isinstance(cond, Future):
        cond = cond.done
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if isinstance(on, Graph):
            on.check()
        if cond():
            return True
        if isinstance(on, Executor):
            on.spin_once(timeout_sec=step)
        else:
            time.sleep(step)
    return cond()


@contextmanager
def killed_on_exit(proc: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``proc``, killed when the block leaves while it still runs (a failed assertion)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


class OutputWatcher:
    """Collects a child's merged stdout/stderr lines on a thread; ``wait_line(text, timeout)``
    returns once a line containing ``text`` arrived (False at the timeout or the child's end)."""

    def __init__(self, proc: subprocess.Popen):
        import threading
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._done = False
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def wait_line(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not any(text in line for line in self.lines):
                left = deadline - time.monotonic()
                if self._done or left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def text(self) -> str:
        self._thread.join(timeout=5)
        with self._cond:
            return "".join(self.lines)


#: the synthetic scene of the graph tests (6 cameras, reduced mesh for speed)
SCENE = dict(rig="sportcenter6", frames=10, seed=3, difficulty="easy", num_vertices=2000)
#: publish rate of the test players, Hz: the frame period must stay below the association's
#: max_wait (a camera silent for longer than max_wait is treated as dead by the synchroniser)
RATE_HZ = 5.0


class Graph:
    """Nodes on a private Context, spun by one executor in a background thread."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.executor = make_executor(self.context)  # the nodes' own (ros.process)
        self.nodes: list[Any] = []
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            while not self._stop.is_set() and self.context.ok():
                self.executor.spin_once(timeout_sec=0.02)
        except BaseException as e:  # noqa: BLE001 - reported by check()
            self._error = e

    def add(self, cls: Callable[..., Any], params: dict[str, Any], **kwargs: Any):
        """Create a node of ``cls`` with parameter overrides and add it to the executor."""
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        node = cls(context=self.context, parameter_overrides=overrides, **kwargs)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def client(self, name: str = "test_client"):
        node = rclpy.create_node(name, context=self.context)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def check(self) -> None:
        assert self._error is None, f"executor thread died: {self._error!r}"
        assert self.thread.is_alive()

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10)
        if self.nodes:  # all of the context's nodes go: its discovery may stop (ros/fastdds.py)
            detach_discovery_listener(self.nodes[0])
        for node in self.nodes:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=2.0)
        rclpy.shutdown(context=self.context)
        assert not self.thread.is_alive(), "executor thread did not stop"


class Recorder:
    """Collects messages of a topic (decoded by ``decode``) keyed by header stamp."""

    def __init__(self, node, msg_type, topic: str, qos, decode: Callable[[Any], Any] = lambda m: m):
        self.lock = threading.Lock()
        self.by_stamp: dict[int, Any] = {}
        self.arrival: dict[int, float] = {}  # time.monotonic() of each stamp's first message
        self.all: list[Any] = []
        self.rejected: list[wire.WireError] = []
        self.decode = decode
        self.sub = node.create_subscription(msg_type, topic, self._cb, qos)

    def _cb(self, msg) -> None:
        try:
            item = self.decode(msg)
        except wire.WireError as e:  # a robustness test publishes garbage on this topic
            with self.lock:
                self.rejected.append(e)
            return
        header = getattr(msg, "header", None)
        if header is None and getattr(msg, "markers", None):  # MarkerArray: its markers' stamp
            header = msg.markers[0].header
        with self.lock:
            self.all.append(item)
            if header is not None:
                stamp = wire.stamp_to_ns(header.stamp)
                self.by_stamp[stamp] = item
                self.arrival.setdefault(stamp, time.monotonic())

    def has(self, stamp_ns: int) -> bool:
        with self.lock:
            return stamp_ns in self.by_stamp

    def count(self) -> int:
        with self.lock:
            return len(self.all)


class DiagnosticsReader(DiagnosticsTable):
    """Latest /diagnostics values per node (status name = fully qualified node name)."""

    def get(self, node_name: str) -> dict[str, str]:
        with self.lock:
            return dict(self.latest.get(node_name, {}))

    def value(self, node_name: str, key: str, default: float = 0.0) -> float:
        return float(self.get(node_name).get(key, default))

    def wait_value(self, node_name: str, key: str, pred: Callable[[float], bool],
                   timeout: float = 10.0, graph: Graph | None = None) -> float:
        ok = wait_for(lambda: pred(self.value(node_name, key, float("nan"))), timeout, graph)
        assert ok, f"{node_name} {key}: {self.get(node_name)}"
        return self.value(node_name, key)


def wait_links_matched(diags: DiagnosticsReader, links, timeout: float = 30.0,
                       on: Any = None) -> None:
    """Until every link is matched at the node's end too (its /diagnostics): what is sent
    before both ends matched is lost, and the publisher's own count only says its end."""
    assert wait_for(lambda: not unmatched_links(diags.snapshot(), links), timeout, on), \
        f"not matched: {unmatched_links(diags.snapshot(), links)}"


class DetectionPlayer:
    """Publishes FrameDetections as /<cam>/detections PointCloud2 messages."""

    def __init__(self, node, cameras):
        self.pubs = {c: node.create_publisher(PointCloud2, f"/{c}/detections", DATA_QOS)
                     for c in cameras}

    def wait_matched(self, timeout: float = 20.0) -> bool:
        return wait_for(lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values()),
                        timeout)

    def publish(self, dets) -> None:
        self.pubs[dets.camera].publish(wire.detections_to_msg(dets))

    def publish_msg(self, camera: str, msg: PointCloud2) -> None:
        self.pubs[camera].publish(msg)


def play(g: dict[str, Any], scene, frames, cameras=None, rate_hz: float = RATE_HZ,
         stamp_of: Callable[[int], int] | None = None) -> list[int]:
    """Publish the detections of ``frames`` at ``rate_hz``; returns the stamps."""
    cams = cameras or g["assoc"].rig.names
    stamps, t0 = [], time.monotonic()
    for i, f in enumerate(frames):
        while time.monotonic() < t0 + i / rate_hz:
            time.sleep(0.005)
        cams_f = cams(f) if callable(cams) else cams
        for cam in cams_f:
            dets = scene.detections(cam, f)
            if stamp_of is not None:
                dets.stamp_ns = stamp_of(i)
            g["player"].publish(dets)
        stamps.append(stamp_of(i) if stamp_of is not None else scene.stamp_ns(f))
    return stamps


#: association thresholds of the graph tests: the paper's gates, tau_det 0.5 because the sim's
#: detection scores straddle 0.9 (with 0.9 only ~70% of the players get 4 views)
ASSOC = dict(rig="sportcenter6", tau_det=0.5, tau_reproj_bbox=10.0, tau_mesh=8.0, k_min=4,
             slop=0.005, max_wait=1.0, min_cameras=2, diagnostics_period=0.2,
             keep_every_set=True)
#: the live overload policy (skip stale frames), which the graph tests turn off above: they
#: check every frame, and on one executor shared by both nodes and the test's own
#: subscriptions a node waits for the other's work as if it were behind; test_overload.py
#: and test_live_receive.py test the policy with these
LIVE_POLICY = dict(keep_every_set=False)


def pipeline_params(**extra: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    assoc = dict(ASSOC)
    tri = dict(rig="sportcenter6", tau_kps=20.0, output_convention="sportcenter_13",
               track_min_hits=3, marker_lifetime=0.5, diagnostics_period=0.2,
               keep_every_set=True)
    assoc.update(extra.get("association", {}))
    tri.update(extra.get("triangulation", {}))
    return assoc, tri


def stall(graph: Graph, release: threading.Event) -> threading.Event:
    """Block the graph's executor (one callback that waits for ``release``, at most 30 s): the
    node under test is busy, as under CPU starvation, while DDS keeps receiving. Returns an
    Event set once the executor is blocked."""
    started = threading.Event()
    node = graph.client("stall")
    timer = None

    def block() -> None:
        timer.cancel()
        started.set()
        release.wait(30.0)

    timer = node.create_timer(0.01, block)
    return started


def start_pipeline(graph: Graph, **extra: Any):
    from maem_ros.ros.association_node import AssociationNode
    from maem_ros.ros.triangulation_node import TriangulationNode

    assoc_p, tri_p = pipeline_params(**extra)
    assoc = graph.add(AssociationNode, assoc_p)
    tri = graph.add(TriangulationNode, tri_p)
    client = graph.client()
    player = DetectionPlayer(client, assoc.rig.names)
    # the test's recorders keep 100 messages: a burst must not be lost here, in the test
    clusters = Recorder(client, PointCloud2, "/maem/clusters", RELIABLE,
                        lambda m: wire.msg_to_clusters(m, "/maem/clusters", len(assoc.rig)))
    poses = Recorder(client, PointCloud2, "/maem/poses", RELIABLE,
                     lambda m: wire.msg_to_poses(m, "/maem/poses"))
    markers = Recorder(client, MarkerArray, "/maem/skeletons", RELIABLE)
    diags = DiagnosticsReader(client)
    assert player.wait_matched(), "association did not subscribe to every camera"
    assert wait_for(lambda: poses.sub.get_publisher_count() > 0 and
                    clusters.sub.get_publisher_count() > 0, 20.0)
    wait_links_matched(diags, fusion_links(assoc.rig.names, image_topic=None))
    return dict(assoc=assoc, tri=tri, client=client, player=player, clusters=clusters,
                poses=poses, markers=markers, diags=diags)


def match_players(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hungarian on MPJPE (m), pairs < 0.5 m: (pred index, gt index, mpjpe)."""
    from scipy.optimize import linear_sum_assignment
    if len(pred) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    d = np.linalg.norm(pred[:, None] - gt[None], axis=-1)
    with np.errstate(invalid="ignore"):
        cost = np.nanmean(d, axis=-1)
    cost = np.where(np.isfinite(cost), cost, 1e9)
    r, c = linear_sum_assignment(cost)
    keep = cost[r, c] < 0.5
    return r[keep], c[keep], cost[r, c][keep]


def offline(scene, frames: range, temporal: bool = False):
    """The core pipeline run directly on the wire-roundtripped detections (what the nodes see):
    track-assisted association with its track ids, or per-frame + the post-hoc tracker."""
    from maem_ros.core.association.pipeline import AssociationParams
    from maem_ros.core.tracking.joint_filter import JointFilterParams, filter_and_score
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    from maem_ros.core.tracking.tracks import Tracker
    from maem_ros.core.triangulation.ransac import TriangulationParams, triangulate

    ap = AssociationParams.from_mapping(ASSOC)
    stage = TemporalAssociator(scene.rig, ap, TemporalParams(temporal=temporal))
    tracker = Tracker(gate_m=0.5, min_hits=3, timeout_s=1.0)
    joint_filter = JointFilterParams().make()
    tri = TriangulationParams(tau_kps=20.0)
    out = []
    for f in frames:
        dets = {c: wire.msg_to_detections(wire.detections_to_msg(scene.detections(c, f)), "t")
                for c in scene.rig.names}
        res = stage.step(dets, scene.stamp_ns(f))
        poses = triangulate(scene.rig, dets, res.clusters, tri)
        joints = SPORTCENTER_13.select(poses.joints)
        cov = SPORTCENTER_13.select(poses.joint_cov.reshape(len(poses), -1, 9))
        cov = cov.reshape(cov.shape[:2] + (3, 3))
        ids = res.track_ids if temporal else tracker.update(scene.stamp_ns(f), joints)
        joints, _, _ = filter_and_score(scene.stamp_ns(f), np.asarray(ids), joints, cov,
                                        poses.detection_scores, joint_filter, tri.pose_score,
                                        tri.score_ref_m)
        out.append((res.clusters, joints, ids))
    return out


def fresh_detections(scene, camera: str, frame: int) -> FrameDetections:
    """A private copy (the scene's detections share arrays with its cache)."""
    d = scene.detections(camera, frame)
    return d.select(np.arange(d.n))


def bad_messages(scene) -> list[tuple[str, PointCloud2]]:
    """(expected drop reason, message) published on /camera_0/detections."""
    out = []

    def base():
        return wire.detections_to_msg(scene.detections("camera_0", 1))

    m = base()
    m.fields = [f for f in m.fields if f.name != "verts2d"]
    out.append(("missing_field", m))
    m = base()
    m.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype,
                           count=f.count - (3 if f.name == "kpts3d" else 0)) for f in m.fields]
    out.append(("bad_count", m))  # kpts3d count 3J-3 with kpts2d 2J
    m = base()
    m.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype,
                           count=f.count + (3 if f.name == "kpts3d" else 0)) for f in m.fields]
    out.append(("bad_layout", m))  # kpts3d now runs into verts2d
    d = fresh_detections(scene, "camera_0", 1)
    d.kpts2d[0, 3, 1] = np.inf  # NaN would be a keypoint not seen
    out.append(("nonfinite", wire.detections_to_msg(d)))
    m = base()
    m.data = array.array("B")
    out.append(("bad_size", m))
    m = base()
    m.header.frame_id = "camera_42"
    out.append(("unknown_camera", m))
    m = base()
    m.header.frame_id = "camera_1"
    out.append(("camera_mismatch", m))
    d = fresh_detections(scene, "camera_0", 1)
    d.bboxes[0, 2] = d.bboxes[0, 0] - 1
    out.append(("inverted_bbox", wire.detections_to_msg(d)))
    return out
