"""Cold-start study: seconds from starting ``maem-association`` until it published the clusters
of its first frame set, and the parts of it.

    python scripts/cold_start.py [--params config/demo.yaml] [--wire f32] [--runs 1]

Starts the association node (the console script, as a user does), publishes the synthetic
scene's detections of all cameras every 0.1 s from this process (from the moment the node's
subscriptions match) and listens to /maem/clusters. Prints, per run: ``ready_s`` (start -> the
node's subscriptions matched: imports, kernels loaded or compiled, DDS), ``first_clusters_s``
(start -> first /maem/clusters message), the node's CPU seconds until then, and whether numba
compiled (the node's log says nothing about it; compare a run after ``maem-warmup`` with one
after deleting the caches: ``find maem_ros -name '*.nb[ic]' -delete``). Set ROS_DOMAIN_ID.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import PointCloud2

from maem_ros.ros import wire
from maem_ros.ros.qos import DATA_QOS
from maem_ros.sim.scene import Scene, SceneConfig

SCENE = dict(rig="sportcenter6", frames=20, seed=3, difficulty="easy", num_vertices=18439)


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a running process (/proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_run(params: str, wire_layout: str, scene: Scene, timeout_s: float) -> dict:
    exe = Path(sys.executable).parent / "maem-association"
    node = rclpy.create_node("cold_start_probe")
    pubs = {c: node.create_publisher(PointCloud2, f"/{c}/detections", DATA_QOS)
            for c in scene.rig.names}
    got: list[float] = []
    node.create_subscription(PointCloud2, "/maem/clusters",
                             lambda m: got.append(time.monotonic()), DATA_QOS)
    msgs = [{c: wire.detections_to_msg(scene.detections(c, k), wire_layout)
             for c in scene.rig.names} for k in range(SCENE["frames"])]
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    t0 = time.monotonic()
    proc = subprocess.Popen([str(exe), "--ros-args", "--params-file", params],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ready = cpu_ready = None
    k = 0
    try:
        while not got and time.monotonic() - t0 < timeout_s and proc.poll() is None:
            ex.spin_once(timeout_sec=0.1)
            if ready is None and all(p.get_subscription_count() for p in pubs.values()):
                ready, cpu_ready = time.monotonic() - t0, cpu_seconds(proc.pid)
            if ready is not None:
                for c, p in pubs.items():
                    p.publish(msgs[k % len(msgs)][c])
                k += 1
        first = got[0] - t0 if got else None
        cpu_first = cpu_seconds(proc.pid) if proc.poll() is None else None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        ex.shutdown()
        node.destroy_node()
    return {"ready_s": ready, "first_clusters_s": first, "node_cpu_s_at_ready": cpu_ready,
            "node_cpu_s_at_first_clusters": cpu_first, "frame_sets_published": k,
            "load_average_1min": os.getloadavg()[0]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--params", default=str(Path(__file__).resolve().parents[1] / "config" /
                                           "demo.yaml"))
    p.add_argument("--wire", default="f32", choices=("f32", "q4"))
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--timeout", type=float, default=900.0)
    a = p.parse_args()
    scene = Scene(SceneConfig(**SCENE))
    rclpy.init()
    try:
        for _ in range(a.runs):
            print(json.dumps(one_run(a.params, a.wire, scene, a.timeout)), flush=True)
    finally:
        rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
