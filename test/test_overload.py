"""The live overload policy in the nodes (issue 33): a node stalled under steady traffic skips
the stale frame sets, counted, and publishes the newest ones; a lockstep replay skips nothing.

In process on a private Context (helpers_ros.Graph); maem-play runs as the user runs it (a
subprocess). Every wait has a timeout; the only time bounds are generous ones."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import PointCloud2

from helpers_ros import (LIVE_POLICY, RELIABLE, DiagnosticsReader, Recorder, killed_on_exit,
                         stall, start_pipeline, wait_for)
from maem_ros import bagio
from maem_ros.ros import wire

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

T0 = 1_700_000_000_000_000_000
#: steady traffic of the stall test: 20 Hz (stamps and publishing); the automatic backlog
#: bound is then 4 periods, 200 ms
RATE_HZ = 20.0
PERIOD_NS = int(1e9 / RATE_HZ)


class SteadyTraffic:
    """Every camera's detections at RATE_HZ from a thread (the scene's frames in turn, stamps
    T0 + i / RATE_HZ), until stopped; ``sent`` is the number of frames published."""

    def __init__(self, g: dict, scene):
        self.g, self.scene = g, scene
        self.cams = g["assoc"].rig.names
        self.msgs = {(c, f): wire.detections_to_msg(scene.detections(c, f))
                     for c in self.cams for f in range(scene.num_frames)}
        self.sent = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def stamp(i: int) -> int:
        return T0 + i * PERIOD_NS

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self.stop.is_set():
            i = self.sent
            delay = t0 + i / RATE_HZ - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)
                continue
            for c in self.cams:
                m = self.msgs[(c, i % self.scene.num_frames)]
                m.header = wire.make_header(self.stamp(i), c)
                self.g["player"].publish_msg(c, m)
            self.sent = i + 1

    def run_for(self, seconds: float) -> None:
        time.sleep(seconds)


class Listener:
    """The test's own clusters, poses and /diagnostics subscriptions, spun by an executor
    thread of their own: they keep up while the graph's executor is stalled or saturated
    (on the graph's executor they would fall behind the nodes they observe)."""

    def __init__(self, graph):
        self.node = rclpy.create_node("overload_listener", context=graph.context)
        self.clusters = Recorder(self.node, PointCloud2, "/maem/clusters", RELIABLE)
        self.poses = Recorder(self.node, PointCloud2, "/maem/poses", RELIABLE)
        self.diags = DiagnosticsReader(self.node)
        self.executor = SingleThreadedExecutor(context=graph.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        assert wait_for(lambda: self.clusters.sub.get_publisher_count() > 0
                        and self.poses.sub.get_publisher_count() > 0, 20.0)

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10.0)
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown(timeout_sec=2.0)
        assert not self.thread.is_alive(), "listener thread did not stop"


def test_a_node_stalled_for_a_second_publishes_the_newest_sets_and_counts_the_skipped(
        graph, scene):
    """Steady 20 Hz traffic; the executor is blocked for 1 s (a collection, a busy
    neighbour): ~20 frame sets wait. Afterwards the association publishes the newest set
    within a bounded time instead of working through the stale ones, every set it did not
    process is counted dropped/behind (processed + skipped = sets made; a frame whose
    messages the synchroniser could not hold has them counted), and /diagnostics says it was
    behind and for how long."""
    g = start_pipeline(graph, association=LIVE_POLICY, triangulation=LIVE_POLICY)
    listener = Listener(graph)
    traffic = SteadyTraffic(g, scene)
    try:
        _stall_under_traffic(graph, traffic, listener)
    finally:
        traffic.stop.set()
        traffic.thread.join(timeout=10.0)
        listener.close()


def _stall_under_traffic(graph, traffic: SteadyTraffic, listener: Listener) -> None:
    clusters, d = listener.clusters, listener.diags
    traffic.thread.start()
    release = threading.Event()
    try:
        traffic.run_for(1.0)
        started = stall(graph, release)
        assert wait_for(started.is_set, 10.0)
        first_stalled = traffic.sent
        time.sleep(1.0)
        newest = traffic.sent - 1  # the newest frame published when the stall ends
        release.set()
        assert wait_for(lambda: any(s >= traffic.stamp(newest) for s in
                                    list(clusters.by_stamp)), 10.0, graph), \
            f"no clusters of frame {newest} or later within 10 s of the stall's end"
        traffic.run_for(1.5)
    finally:
        release.set()
        traffic.stop.set()
        traffic.thread.join(timeout=10.0)
    sent = traffic.sent
    last = traffic.stamp(sent - 1)
    assert wait_for(lambda: listener.poses.has(last), 20.0, graph), "the newest frame skipped"
    cams = len(traffic.cams)

    def accounted(kv: dict[str, str]) -> bool:
        """Every message received, every set processed or skipped, and a frame that made no
        set has its messages counted (the diagnostics of one moment: all counters agree)."""
        drops = {k.split("/", 1)[1]: int(v) for k, v in kv.items() if k.startswith("dropped/")}
        sets = int(kv.get("count/sync_sets", -1))
        return (int(kv.get("received/camera_0/detections", -1)) == sent
                and int(kv.get("frames_processed", -1)) + drops.get("behind", 0) == sets
                and (sent - sets) * cams <= sum(n for r, n in drops.items() if r != "behind"))

    wait_for(lambda: accounted(d.get("/association")), 20.0, graph)
    kv = d.get("/association")
    assert accounted(kv), kv
    # nothing but skipped sets and messages the synchroniser or DDS could not hold is lost
    assert all(k[len("dropped/"):] in ("behind", "dds_lost") or k.startswith("dropped/sync_")
               for k in kv if k.startswith("dropped/")), kv
    no_set = sent - int(kv["count/sync_sets"])
    stalled = newest - first_stalled + 1
    assert int(kv["dropped/behind"]) + no_set >= stalled // 2, (stalled, kv)
    assert kv["backlog/policy"] == "skip stale" and float(kv["backlog/bound_ms"]) == \
        pytest.approx(4 * PERIOD_NS / 1e6, rel=0.05), kv
    d.wait_value("/association", "behind/episodes", lambda v: v >= 1, graph=graph)
    assert float(d.get("/association")["behind/longest_s"]) > 0
    skipped = {traffic.stamp(i) for i in range(first_stalled, newest)} - set(clusters.by_stamp)
    assert len(skipped) >= stalled // 2  # the stale sets of the stall are the skipped ones


def _detections_bag(path: Path, scene, frames: int, fps: float) -> list[int]:
    """A bag of every camera's /<cam>/detections (the scene's frames in turn, stamps at
    ``fps``), as maem-record writes a live graph's input; returns the stamps."""
    stamps = [T0 + int(round(i * 1e9 / fps)) for i in range(frames)]
    with bagio.BagWriter(path) as bag:
        for i, stamp in enumerate(stamps):
            for cam in scene.rig.names:
                dets = scene.detections(cam, i % scene.num_frames)
                dets.stamp_ns = stamp
                bag.write(f"/{cam}/detections", wire.detections_to_msg(dets), stamp)
    return stamps


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "free-running"])
def test_a_lockstep_replay_faster_than_real_time_skips_nothing(graph, scene, tmp_path, lockstep):
    """maem-play of a 60 fps detections bag at 10x real time into the nodes with their live
    default policy: in lockstep (each frame when the last one's poses came) every frame gets
    its clusters and poses and nothing is skipped, and the player says so; free-running, the
    nodes fall behind and skip frames, each counted (the player warns about it)."""
    g = start_pipeline(graph, association=LIVE_POLICY, triangulation=LIVE_POLICY)
    stamps = _detections_bag(tmp_path / "bag", scene, 24, 60.0)
    args = ["--lockstep", "/maem/poses", "--lockstep-timeout", "20"] if lockstep else []
    cmd = [sys.executable, "-m", "maem_ros.ros.player_node", str(tmp_path / "bag"),
           "--rate", "10", "--wait-subscribers", "20", "--delay", "0.3", *args]
    with killed_on_exit(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         text=True, env=dict(os.environ))) as proc:
        assert wait_for(lambda: proc.poll() is not None, 120.0, graph), "maem-play did not end"
        out = proc.communicate(timeout=10)[0]
    assert proc.returncode == 0, out
    d = g["diags"]
    assert wait_for(lambda: g["clusters"].has(stamps[-1]), 20.0, graph), out
    d.wait_value("/association", "frames_processed",
                 lambda v: v + d.value("/association", "dropped/behind") == len(stamps),
                 timeout=20.0, graph=graph)
    behind = d.value("/association", "dropped/behind")
    if lockstep:
        assert "0 frame(s) timed out; every frame waited for the graph" in out, out
        assert behind == 0 and all(g["clusters"].has(s) for s in stamps)
        assert wait_for(lambda: all(g["poses"].has(s) for s in stamps), 20.0, graph)
        d.wait_value("/triangulation", "frames_processed", lambda v: v == len(stamps),
                     graph=graph)
        assert d.value("/triangulation", "dropped/behind") == 0
    else:
        assert "faster than real time, live nodes skip the frames" in out, out
        assert behind > 0
        assert sum(g["clusters"].has(s) for s in stamps) == len(stamps) - behind
