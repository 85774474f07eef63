"""In-process graph probes for the tools: rclpy nodes that run beside a tool's own code.

:class:`BackgroundNode` is the shared part: a node in a private ``rclpy.Context`` (so the tool
never touches the default context or signal handling), spun by a ``SingleThreadedExecutor`` in a
daemon thread, closed cleanly by :meth:`BackgroundNode.close`. On top of it:

* :class:`ArrivalListener` (maem-demo): first arrival time of each header stamp on the input
  topics (images, or detections) and on /maem/poses, read from the raw CDR bytes (no
  deserialisation), and the nodes' last /diagnostics;
* :class:`ReplayClient` (tools/bench/latency.py): publishes tiny images with given stamps and records
  /maem/poses and /diagnostics.

:class:`DiagnosticsTable` is the one collector of the nodes' last /diagnostics values (a
BackgroundNode's ``watch_diagnostics``, the tests' reader).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import CompressedImage, Image, PointCloud2

from maem_ros.ros import wire
from maem_ros.ros.cli import shutdown_ros
from maem_ros.ros.process import use_shipped_dds_profile
from maem_ros.ros.qos import DATA_QOS, DIAGNOSTICS_QOS, IMAGE_QOS


class BackgroundNode:
    """A node in its own Context, spun in a daemon thread once :meth:`start` is called.

    Create subscriptions/publishers on ``self.node`` first, then ``start()``; ``close()`` stops
    the thread and shuts the context down. ``lock`` guards what the callbacks record.
    """

    def __init__(self, name: str, domain_id: int | None = None):
        use_shipped_dds_profile()
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)

    def start(self) -> BackgroundNode:
        self.thread.start()
        return self

    def watch_diagnostics(self) -> None:
        """Keep each node's last /diagnostics values (``diagnostics``, guarded by ``lock``;
        ``diagnostics_snapshot``); call before ``start()``."""
        self.diagnostics_table = DiagnosticsTable(self.node, self.lock)
        self.diagnostics = self.diagnostics_table.latest

    def diagnostics_snapshot(self) -> dict[str, dict[str, str]]:
        """{node name: {key: value}} of each node's last /diagnostics (watch_diagnostics)."""
        return self.diagnostics_table.snapshot()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(timeout=5)
        self.executor.shutdown(timeout_sec=1.0)
        shutdown_ros(self.node, self.context)

    def __enter__(self) -> BackgroundNode:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DiagnosticsTable:
    """Each node's last /diagnostics values (``latest``: status name, the fully qualified node
    name -> {key: value}), from a subscription on ``node``; ``lock`` guards ``latest``."""

    def __init__(self, node: rclpy.node.Node, lock: threading.Lock | None = None):
        self.lock = lock or threading.Lock()
        self.latest: dict[str, dict[str, str]] = {}
        self.sub = node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, DIAGNOSTICS_QOS)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        with self.lock:
            for st in msg.status:
                self.latest[st.name] = {kv.key: kv.value for kv in st.values}

    def snapshot(self) -> dict[str, dict[str, str]]:
        with self.lock:
            return {k: dict(v) for k, v in self.latest.items()}


def fusion_links(
    cameras: Sequence[str], image_topic: str | None = "image_raw", namespace: str = "", sources: bool = True
) -> list[tuple[str, str]]:
    """The data path's DDS links as ``(node, /diagnostics key)``, each seen from both ends:
    images -> frontends (``image_topic`` under each camera namespace; None: no frontends, the
    detections come from elsewhere) -> association -> triangulation -> /maem/poses, the nodes
    started under ``namespace`` (e.g. "/team"). Names are the shipped defaults (node names,
    ``maem/clusters``, ``maem/poses``). ``sources=False`` leaves out the first hop (the images,
    or without frontends the detections): the links between the graph's own nodes, which can
    be checked before whatever feeds the graph (a bag player) has started."""
    ns = namespace.rstrip("/")
    topic = ns.lstrip("/") + "/" if ns else ""
    assoc, tri = f"{ns}/association", f"{ns}/triangulation"
    links: list[tuple[str, str]] = []
    for c in cameras:
        if image_topic is not None:
            if sources:
                links.append((f"{ns}/{c}/frontend", f"matched_publishers/{topic}{c}/{image_topic}"))
            links.append((f"{ns}/{c}/frontend", f"matched_subscribers/{topic}{c}/detections"))
        if sources or image_topic is not None:
            links.append((assoc, f"matched_publishers/{topic}{c}/detections"))
    return links + [
        (assoc, f"matched_subscribers/{topic}maem/clusters"),
        (tri, f"matched_publishers/{topic}maem/clusters"),
        (tri, f"matched_subscribers/{topic}maem/poses"),
    ]


def unmatched_links(
    diagnostics: Mapping[str, Mapping[str, str]],
    links: Iterable[tuple[str, str]],
    at_least: Mapping[str, int] | None = None,
) -> list[str]:
    """The links whose node has not reported (in its last /diagnostics) at least one matched
    endpoint (``at_least[key]`` for the keys it names), as ``node:key``: a message sent on such
    a link may be lost even though the ROS graph already lists both nodes."""
    at_least = at_least or {}
    return [
        f"{node}:{key}"
        for node, key in links
        if int(diagnostics.get(node, {}).get(key, "0")) < at_least.get(key, 1)
    ]


class ArrivalListener(BackgroundNode):
    """First arrival (``time.monotonic_ns``) of each header stamp on ``image_topics``
    (CompressedImage) and on /maem/poses, subscribed raw: only the CDR header is read."""

    def __init__(
        self,
        image_topics: Sequence[str],
        domain_id: int | None = None,
        name: str = "maem_demo_listener",
        input_type: type = CompressedImage,
    ):
        super().__init__(name, domain_id)
        self.image_t: dict[int, int] = {}
        self.poses_t: dict[int, int] = {}
        qos = IMAGE_QOS if input_type is CompressedImage else DATA_QOS
        self.subs = [
            self.node.create_subscription(input_type, t, self._arrival(self.image_t), qos, raw=True)
            for t in image_topics
        ]
        self.subs.append(
            self.node.create_subscription(
                PointCloud2, "/maem/poses", self._arrival(self.poses_t), DATA_QOS, raw=True
            )
        )
        self.watch_diagnostics()
        self.start()

    def _arrival(self, table: dict[int, int]) -> Callable[[bytes], None]:
        def record(data: bytes) -> None:
            t = time.monotonic_ns()
            with self.lock:
                table.setdefault(wire.cdr_header_stamp_ns(data), t)

        return record

    def count_subscribers(self, topic: str) -> int:
        return self.node.count_subscribers(topic)

    def snapshot(self) -> tuple[dict[int, int], dict[int, int]]:
        """(image arrivals, poses arrivals) by stamp, copies."""
        with self.lock:
            return dict(self.image_t), dict(self.poses_t)


class ReplayClient(BackgroundNode):
    """Publishes a tiny ``/<cam>/image_raw`` per camera for a stamp; records /maem/poses
    (``poses``: stamp -> (perf_counter s at arrival, PoseFrame)) and the last /diagnostics
    values of each node (``diagnostics``)."""

    def __init__(self, cameras: Sequence[str], name: str = "maem_replay"):
        super().__init__(name)
        self.cameras = list(cameras)
        self.image_pubs = {
            c: self.node.create_publisher(Image, f"/{c}/image_raw", IMAGE_QOS) for c in self.cameras
        }
        self.sent: dict[int, float] = {}
        self.poses: dict[int, tuple[float, Any]] = {}
        self.poses_sub = self.node.create_subscription(PointCloud2, "/maem/poses", self._on_poses, DATA_QOS)
        self.watch_diagnostics()
        self.start()

    def _on_poses(self, msg: PointCloud2) -> None:
        t = time.perf_counter()
        pf = wire.msg_to_poses(msg, "/maem/poses")
        with self.lock:
            self.poses.setdefault(pf.stamp_ns, (t, pf))

    def unready(self) -> list[str]:
        """The links of the graph not yet matched at both ends (empty: ready): images ->
        frontends -> association -> triangulation -> us, the nodes' own ends read from their
        /diagnostics."""
        ours = [
            f"images -> /{c}/image_raw" for c, p in self.image_pubs.items() if p.get_subscription_count() == 0
        ]
        if self.poses_sub.get_publisher_count() == 0:
            ours.append("/maem/poses -> us")
        return ours + unmatched_links(self.diagnostics_snapshot(), fusion_links(self.cameras))

    def ready(self) -> bool:
        return not self.unready()

    def wait_ready(self, timeout_s: float, alive: Callable[[], bool] = lambda: True) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.ready():
                return True
            if not alive():
                return False
            time.sleep(0.1)
        return False

    def publish_frame(self, stamp_ns: int, cameras: Sequence[str] | None = None) -> None:
        """One tiny image per camera (default all) with ``stamp_ns``; ``sent`` keeps the time
        of the first image of each stamp."""
        img = np.zeros((2, 2, 3), np.uint8)
        with self.lock:
            self.sent.setdefault(stamp_ns, time.perf_counter())
        for cam in self.cameras if cameras is None else cameras:
            self.image_pubs[cam].publish(wire.bgr_to_image(img, stamp_ns, cam))
