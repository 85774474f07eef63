"""Replay a synthetic scene through the multi-process node graph; report latency, drops, CPU.

    python -m maem_ros.tools.latency --params config/demo.yaml --frames 150 --rate 30

Starts one frontend per rig camera, the association and the triangulation node as separate
processes (``python -m maem_ros.ros.<node> --ros-args --params-file P``), publishes a tiny
``image_raw`` per camera for every scene frame at ``--rate`` Hz with the scene's stamps (the
synthetic backend regenerates the detections from the stamp; the image content is unused), and
listens to /maem/poses. Latency = poses received - first image of that stamp published
(wall clock, this machine). CPU = each node's user+system time during the replay / wall time.
Frames dropped = frames published without a poses message. Accuracy = MPJPE of poses matched to
the scene's players (Hungarian, < 500 mm).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from maem_ros.params import load_node_params, resolve_config_path

NODE_MODULES = {"frontend": "maem_ros.ros.frontend_node",
                "association": "maem_ros.ros.association_node",
                "triangulation": "maem_ros.ros.triangulation_node"}


# ---------------------------------------------------------------------------------------------
# processes
# ---------------------------------------------------------------------------------------------
def node_command(kind: str, params_file: str | Path, namespace: str | None = None) -> list[str]:
    """argv running one node with a params file (``python -m``, works without installing)."""
    cmd = [sys.executable, "-m", NODE_MODULES[kind], "--ros-args", "--params-file", str(params_file)]
    if namespace:
        cmd += ["-r", f"__ns:={namespace}"]
    return cmd


@dataclass
class NodeProcess:
    name: str
    popen: subprocess.Popen
    log: Path

    def cpu_seconds(self) -> float:
        """user + system CPU seconds so far (Linux /proc), NaN when the process is gone."""
        try:
            parts = Path(f"/proc/{self.popen.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class GraphProcesses:
    """The frontend (one per camera), association and triangulation processes of one graph."""

    params_file: Path
    cameras: Sequence[str]
    log_dir: Path
    procs: list[NodeProcess] = field(default_factory=list)

    def start(self) -> "GraphProcesses":
        self.log_dir.mkdir(parents=True, exist_ok=True)
        specs = [(f"frontend_{c}", node_command("frontend", self.params_file, f"/{c}"))
                 for c in self.cameras]
        specs += [(k, node_command(k, self.params_file)) for k in ("association", "triangulation")]
        env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
        for name, cmd in specs:
            log = self.log_dir / f"{name}.log"
            with open(log, "wb") as fh:
                popen = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
            self.procs.append(NodeProcess(name, popen, log))
        return self

    def dead(self) -> list[str]:
        return [p.name for p in self.procs if p.popen.poll() is not None]

    def stop(self, timeout_s: float = 15.0) -> dict[str, int | None]:
        """SIGINT every process, wait up to ``timeout_s``; kill leftovers. Returns exit codes
        (None = had to be killed)."""
        for p in self.procs:
            if p.popen.poll() is None:
                p.popen.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        codes: dict[str, int | None] = {}
        for p in self.procs:
            try:
                codes[p.name] = p.popen.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.popen.kill()
                p.popen.wait(timeout=5)
                codes[p.name] = None
        return codes

    def logs(self, tail: int = 2000) -> str:
        return "\n".join(f"--- {p.name} ---\n{p.log.read_text(errors='replace')[-tail:]}"
                         for p in self.procs if p.log.exists())


# ---------------------------------------------------------------------------------------------
# replay client
# ---------------------------------------------------------------------------------------------
class ReplayClient:
    """A node (own Context) publishing images and recording /maem/poses + /diagnostics."""

    def __init__(self, cameras: Sequence[str]):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import Image, PointCloud2

        from maem_ros.ros.common import DATA_QOS, DIAGNOSTICS_QOS, IMAGE_QOS

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("maem_replay", context=self.context)
        self.cameras = list(cameras)
        self.image_pubs = {c: self.node.create_publisher(Image, f"/{c}/image_raw", IMAGE_QOS)
                           for c in self.cameras}
        self.lock = threading.Lock()
        self.sent: dict[int, float] = {}
        self.poses: dict[int, tuple[float, Any]] = {}
        self.diagnostics: dict[str, dict[str, str]] = {}
        self.poses_sub = self.node.create_subscription(PointCloud2, "/maem/poses", self._on_poses,
                                                       DATA_QOS)
        self.diag_sub = self.node.create_subscription(DiagnosticArray, "/diagnostics",
                                                      self._on_diag, DIAGNOSTICS_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def _on_poses(self, msg) -> None:
        from maem_ros.ros import wire
        t = time.perf_counter()
        pf = wire.msg_to_poses(msg, "/maem/poses")
        with self.lock:
            self.poses.setdefault(pf.stamp_ns, (t, pf))

    def _on_diag(self, msg) -> None:
        with self.lock:
            for st in msg.status:
                self.diagnostics[st.name] = {kv.key: kv.value for kv in st.values}

    def ready(self) -> bool:
        """Every edge of the graph discovered: images -> frontends -> association ->
        triangulation -> us."""
        n = self.node
        return (all(p.get_subscription_count() > 0 for p in self.image_pubs.values())
                and all(n.count_publishers(f"/{c}/detections") > 0 and
                        n.count_subscribers(f"/{c}/detections") > 0 for c in self.cameras)
                and n.count_publishers("/maem/clusters") > 0
                and n.count_subscribers("/maem/clusters") > 0
                and self.poses_sub.get_publisher_count() > 0)

    def wait_ready(self, timeout_s: float, alive=lambda: True) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.ready():
                return True
            if not alive():
                return False
            time.sleep(0.1)
        return False

    def publish_frame(self, stamp_ns: int) -> None:
        from maem_ros.ros import wire
        img = np.zeros((2, 2, 3), np.uint8)
        with self.lock:
            self.sent.setdefault(stamp_ns, time.perf_counter())
        for cam, pub in self.image_pubs.items():
            pub.publish(wire.bgr_to_image(img, stamp_ns, cam))

    def close(self) -> None:
        import rclpy
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


# ---------------------------------------------------------------------------------------------
# params / scene
# ---------------------------------------------------------------------------------------------
def write_params(base: str | Path, out: Path, frontend: dict[str, Any] | None = None,
                 association: dict[str, Any] | None = None,
                 triangulation: dict[str, Any] | None = None) -> Path:
    """Copy a params file with per-node overrides into ``out``."""
    data = yaml.safe_load(resolve_config_path(base).read_text()) or {}
    for node, extra in (("frontend", frontend), ("association", association),
                        ("triangulation", triangulation)):
        if extra:
            key = next((k for k in (f"/**/{node}", node, f"/{node}") if k in data), f"/**/{node}")
            data.setdefault(key, {}).setdefault("ros__parameters", {}).update(extra)
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def make_scene(params_file: Path):
    """The sim Scene the synthetic frontends of ``params_file`` regenerate."""
    from maem_ros.frontend.synthetic import scene_config_dict
    from maem_ros.ros.frontend_node import PARAMS, backend_options
    from maem_ros.sim.scene import Scene, SceneConfig

    p = {s.name: s.default for s in PARAMS}
    p.update(load_node_params(params_file, "frontend"))
    return Scene(SceneConfig.from_dict(scene_config_dict(backend_options(p))))


def match_mpjpe(pred: np.ndarray, gt: np.ndarray,
                max_m: float = 0.5) -> tuple[list[float], list[tuple[int, int]]]:
    """Hungarian on MPJPE (NaN joints ignored); pairs under ``max_m``: (errors m, (pred, gt))."""
    from scipy.optimize import linear_sum_assignment
    if len(pred) == 0 or len(gt) == 0:
        return [], []
    d = np.linalg.norm(pred[:, None] - gt[None], axis=-1)  # (K,P,J)
    with np.errstate(invalid="ignore"):
        cost = np.nanmean(np.where(np.isfinite(d), d, np.nan), axis=-1)
    cost = np.where(np.isfinite(cost), cost, 1e9)
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] < max_m
    return list(cost[rows, cols][keep]), list(zip(rows[keep], cols[keep]))


def expected_stamps(stamps: Sequence[int], max_rate: float) -> list[int]:
    """The stamps frontends with ``max_rate`` (stamp-aligned decimation) process."""
    if max_rate <= 0:
        return list(stamps)
    bucket_ns, out, last = int(round(1e9 / max_rate)), [], None
    for s in stamps:
        if s // bucket_ns != last:
            out.append(s)
            last = s // bucket_ns
    return out


# ---------------------------------------------------------------------------------------------
# replay
# ---------------------------------------------------------------------------------------------
def run(params_file: Path, frames: int, rate_hz: float, log_dir: Path, startup_timeout: float = 120.0,
        drain_s: float = 3.0) -> dict[str, Any]:
    from maem_ros.core.skeleton import get_convention
    from maem_ros.ros.common import load_rig_param

    rig = load_rig_param(load_node_params(params_file, "association").get("rig", ""))
    scene = make_scene(params_file)
    frames = min(frames, scene.num_frames)
    graph = GraphProcesses(params_file, rig.names, log_dir).start()
    client = ReplayClient(rig.names)
    report: dict[str, Any] = {"cameras": len(rig.names), "frames_published": frames, "rate_hz": rate_hz}
    try:
        if not client.wait_ready(startup_timeout, alive=lambda: not graph.dead()):
            raise RuntimeError(f"graph not ready (dead: {graph.dead()})\n{graph.logs()}")
        time.sleep(1.0)  # let the last discovery settle
        cpu0 = {p.name: p.cpu_seconds() for p in graph.procs}
        t0 = time.perf_counter()
        period = 1.0 / rate_hz
        for f in range(frames):
            target = t0 + f * period
            while (now := time.perf_counter()) < target:
                time.sleep(min(target - now, 0.005))
            client.publish_frame(scene.stamp_ns(f))
        deadline = time.perf_counter() + drain_s
        last = scene.stamp_ns(frames - 1)
        while time.perf_counter() < deadline and last not in client.poses:
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        cpu1 = {p.name: p.cpu_seconds() for p in graph.procs}
        time.sleep(1.2)  # one more diagnostics period
    finally:
        codes = graph.stop()
        client.close()
    with client.lock:
        sent, poses, diags = dict(client.sent), dict(client.poses), dict(client.diagnostics)
    lat = np.array([(poses[s][0] - t) * 1e3 for s, t in sent.items() if s in poses])
    conv = get_convention(load_node_params(params_file, "triangulation")
                          .get("output_convention", "sportcenter_13"))
    errors = []
    for f in range(frames):
        s = scene.stamp_ns(f)
        if s in poses:
            gt = conv.select(scene.gt_keypoints(f)[scene.is_player])
            errors += match_mpjpe(poses[s][1].joints, gt)[0]
    max_rate = float(load_node_params(params_file, "frontend").get("max_rate", 0.0) or 0.0)
    expected = expected_stamps([scene.stamp_ns(f) for f in range(frames)], max_rate)
    report.update({
        "load_average_1min": round(os.getloadavg()[0], 2),
        "frontend_max_rate_hz": max_rate,
        "frames_expected": len(expected),
        "poses_received": int(len(lat)),
        "frames_dropped": int(sum(s not in poses for s in expected)),
        "latency_ms_median": float(np.median(lat)) if len(lat) else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
        "latency_ms_max": float(lat.max()) if len(lat) else None,
        "mpjpe_mm_mean": float(np.mean(errors) * 1e3) if errors else None,
        "cpu_percent": {n: round(100 * (cpu1[n] - cpu0[n]) / wall, 1) for n in cpu0},
        "exit_codes": codes,
        "nodes": {n: {k: v for k, v in d.items() if k.startswith(("dropped", "missing/", "frames_"))
                      or (k.startswith("time_ms/") and k.endswith("/median"))}
                  for n, d in sorted(diags.items())},
    })
    return report


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="maem-latency", description=__doc__.splitlines()[0])
    ap.add_argument("--params", default="demo.yaml", help="params file (default config/demo.yaml)")
    ap.add_argument("--frames", type=int, default=150, help="scene frames to replay")
    ap.add_argument("--rate", type=float, default=30.0, help="publish rate, Hz")
    ap.add_argument("--difficulty", default=None, choices=("none", "easy", "medium", "hard"))
    ap.add_argument("--num-vertices", type=int, default=None, help="mesh vertices per person")
    ap.add_argument("--max-rate", type=float, default=None,
                    help="frontend max_rate, Hz (stamp-aligned decimation)")
    ap.add_argument("--max-wait", type=float, default=None, help="association max_wait, s")
    ap.add_argument("--log-dir", type=Path, default=None, help="node logs (default: a temp dir)")
    ap.add_argument("--json", action="store_true", help="print the report as JSON")
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="maem_latency_"))
    fe: dict[str, Any] = {"frames": max(a.frames, 1)}
    if a.difficulty:
        fe["difficulty"] = a.difficulty
    if a.num_vertices:
        fe["num_vertices"] = a.num_vertices
    if a.max_rate:
        fe["max_rate"] = a.max_rate
    assoc = {"max_wait": a.max_wait} if a.max_wait else None
    params = write_params(a.params, tmp / "params.yaml", frontend=fe, association=assoc)
    report = run(params, a.frames, a.rate, a.log_dir or tmp / "logs")
    print(json.dumps(report, indent=2) if a.json else yaml.safe_dump(report, sort_keys=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
