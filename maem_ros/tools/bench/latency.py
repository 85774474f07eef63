"""Replay a synthetic scene through the multi-process node graph; report latency, drops, CPU.

    python -m maem_ros.tools.bench.latency --params config/demo.yaml --frames 150 --rate 30

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
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.optimize import linear_sum_assignment

from maem_ros.core.skeleton import get_convention
from maem_ros.frontend.synthetic import scene_config_dict
from maem_ros.params import load_node_params, resolve_config_path
from maem_ros.ros.frontend_node import PARAMS, backend_options
from maem_ros.ros.params import load_rig_param
from maem_ros.ros.probe import ReplayClient
from maem_ros.sim.scene import Scene, SceneConfig
from maem_ros.tools.cli import add_json_argument, add_params_argument, check_params_file, fail, print_report
from maem_ros.tools.processes import Proc, ProcessGroup, node_command

PROG = "maem-latency"


# ---------------------------------------------------------------------------------------------
# processes
# ---------------------------------------------------------------------------------------------
@dataclass
class GraphProcesses:
    """The frontend (one per camera), association and triangulation processes of one graph."""

    params_file: Path
    cameras: Sequence[str]
    log_dir: Path
    group: ProcessGroup = field(init=False)

    def __post_init__(self) -> None:
        self.group = ProcessGroup(self.log_dir, dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1"))

    @property
    def procs(self) -> list[Proc]:
        return list(self.group.procs.values())

    def start(self) -> GraphProcesses:
        for c in self.cameras:
            self.group.start(f"frontend_{c}", node_command("frontend", self.params_file, f"/{c}"))
        for kind in ("association", "triangulation"):
            self.group.start(kind, node_command(kind, self.params_file))
        return self

    def dead(self) -> list[str]:
        return list(self.group.dead())

    def stop(self, timeout_s: float = 15.0) -> dict[str, int | None]:
        """SIGINT every process, wait up to ``timeout_s``; kill leftovers. Returns exit codes
        (None = had to be killed)."""
        return self.group.stop(timeout_s=timeout_s)

    def logs(self, tail: int = 2000) -> str:
        return self.group.logs(tail)


# ---------------------------------------------------------------------------------------------
# params / scene
# ---------------------------------------------------------------------------------------------
def write_params(
    base: str | Path,
    out: Path,
    frontend: dict[str, Any] | None = None,
    association: dict[str, Any] | None = None,
    triangulation: dict[str, Any] | None = None,
) -> Path:
    """Copy a params file with per-node overrides into ``out``."""
    data = yaml.safe_load(resolve_config_path(base).read_text()) or {}
    for node, extra in (
        ("frontend", frontend),
        ("association", association),
        ("triangulation", triangulation),
    ):
        if extra:
            key = next((k for k in (f"/**/{node}", node, f"/{node}") if k in data), f"/**/{node}")
            data.setdefault(key, {}).setdefault("ros__parameters", {}).update(extra)
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def make_scene(params_file: Path) -> Scene:
    """The sim Scene the synthetic frontends of ``params_file`` regenerate."""
    p = {s.name: s.default for s in PARAMS}
    p.update(load_node_params(params_file, "frontend"))
    return Scene(SceneConfig.from_dict(scene_config_dict(backend_options(p))))


def match_mpjpe(
    pred: np.ndarray, gt: np.ndarray, max_m: float = 0.5
) -> tuple[list[float], list[tuple[int, int]]]:
    """Hungarian on MPJPE (NaN joints ignored); pairs under ``max_m``: (errors m, (pred, gt))."""
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


@dataclass(frozen=True)
class Faults:
    """Injected faults: ``lag_camera`` gets its images ``lag_s`` after the others (slow link,
    clock offset); every ``stale_every_s`` one camera also gets an image with a stale stamp
    (stamp 0, then alternately a 1 s old duplicate)."""

    lag_camera: str | None = None
    lag_s: float = 0.0
    stale_every_s: float = 0.0

    def schedule(
        self, stamps: Sequence[int], cameras: Sequence[str], rate_hz: float
    ) -> list[tuple[float, int, tuple[str, ...]]]:
        """(seconds after the start, stamp, cameras) publish events, in time order."""
        period = 1.0 / rate_hz
        on_time = tuple(c for c in cameras if c != self.lag_camera)
        events = [(f * period, s, on_time) for f, s in enumerate(stamps)]
        if self.lag_camera:
            events += [(f * period + self.lag_s, s, (self.lag_camera,)) for f, s in enumerate(stamps)]
        if self.stale_every_s > 0:
            step = max(1, int(round(self.stale_every_s * rate_hz)))
            for k, f in enumerate(range(step, len(stamps), step)):
                stale = 0 if k % 2 == 0 else stamps[max(0, f - int(round(rate_hz)))]
                events.append((f * period + 0.5 * period, stale, (on_time[0],)))
        return sorted(events, key=lambda e: e[0])


def add_fault_arguments(p: argparse.ArgumentParser) -> None:
    """The injected faults' options (--lag-camera, --lag-ms, --stale-every) of the graph replays
    (this module's main, maem-soak)."""
    p.add_argument("--lag-camera", default=None, help="fault: this camera's images come late")
    p.add_argument("--lag-ms", type=float, default=300.0, help="fault: its lag, ms")
    p.add_argument(
        "--stale-every",
        type=float,
        default=0.0,
        help="fault: every this many s one camera gets a stale stamp (0 = off)",
    )


def faults_from(a: argparse.Namespace) -> Faults:
    """The :class:`Faults` of parsed :func:`add_fault_arguments` options."""
    return Faults(a.lag_camera, a.lag_ms / 1e3, a.stale_every)


# ---------------------------------------------------------------------------------------------
# replay
# ---------------------------------------------------------------------------------------------
def _pose_errors(params_file: Path, scene, poses: dict, frames: int) -> list[float]:
    """MPJPE (m) of every received pose against the scene's ground truth, matched per frame,
    in the triangulation's output convention."""
    conv = get_convention(
        load_node_params(params_file, "triangulation").get("output_convention", "sportcenter_13")
    )
    errors: list[float] = []
    for f in range(frames):
        s = scene.stamp_ns(f)
        if s in poses:
            gt = conv.select(scene.gt_keypoints(f)[scene.is_player])
            errors += match_mpjpe(poses[s][1].joints, gt)[0]
    return errors


def run(
    params_file: Path,
    frames: int,
    rate_hz: float,
    log_dir: Path,
    startup_timeout: float = 120.0,
    drain_s: float = 3.0,
    faults: Faults = Faults(),
) -> dict[str, Any]:
    rig = load_rig_param(load_node_params(params_file, "association").get("rig", ""))
    scene = make_scene(params_file)
    frames = min(frames, scene.num_frames)
    graph = GraphProcesses(params_file, rig.names, log_dir).start()
    try:
        client = ReplayClient(rig.names)
    except BaseException:
        graph.stop()
        raise
    report: dict[str, Any] = {"cameras": len(rig.names), "frames_published": frames, "rate_hz": rate_hz}
    try:
        if not client.wait_ready(startup_timeout, alive=lambda: not graph.dead()):
            raise RuntimeError(
                f"graph not ready (dead: {graph.dead()}; not matched: {client.unready()})\n{graph.logs()}"
            )
        cpu0 = {p.name: p.cpu_seconds() for p in graph.procs}
        t0 = time.perf_counter()
        stamps = [scene.stamp_ns(f) for f in range(frames)]
        for offset, stamp, cams in faults.schedule(stamps, rig.names, rate_hz):
            target = t0 + offset
            while (now := time.perf_counter()) < target:
                time.sleep(min(target - now, 0.005))
            client.publish_frame(stamp, cams)
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
    valid = set(scene.stamp_ns(f) for f in range(frames))
    lat = np.array([(poses[s][0] - t) * 1e3 for s, t in sent.items() if s in poses and s in valid])
    errors = _pose_errors(params_file, scene, poses, frames)
    max_rate = float(load_node_params(params_file, "frontend").get("max_rate", 0.0) or 0.0)
    expected = expected_stamps([scene.stamp_ns(f) for f in range(frames)], max_rate)
    report.update(
        {
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
            "nodes": {
                n: {
                    k: v
                    for k, v in d.items()
                    if k.startswith(("dropped", "missing/", "frames_"))
                    or (k.startswith("time_ms/") and k.endswith("/median"))
                }
                for n, d in sorted(diags.items())
            },
        }
    )
    return report


def sync_model(
    cameras: Sequence[str],
    frames: int,
    rate_hz: float,
    faults: Faults,
    max_wait_s: float = 0.15,
    slop_s: float = 0.02,
    max_lag_s: float = 0.0,
    poll_s: float = 0.01,
    delivery_ms: float = 12.0,
    jitter_ms: float = 4.0,
    seed: int = 0,
) -> dict[str, Any]:
    """The association's synchroniser alone on the fault schedule (no processes, no CPU
    contention): each image reaches the synchroniser ``delivery_ms`` (frontend + transport)
    plus exponential jitter (mean ``jitter_ms``) after it is published, in order per camera;
    the synchroniser is polled every ``poll_s`` as the node's timer does. Latency = set emitted
    - first image of the stamp published; a frame is lost when no set holds it."""
    from maem_ros.core.sync import ApproximateTimeSync

    rng = np.random.default_rng(seed)
    stamps = [int(i * 1e9 / rate_hz) + 10**18 for i in range(frames)]
    arrivals, last = [], dict.fromkeys(cameras, 0)
    first_sent: dict[int, int] = {}
    for t, stamp, cams in faults.schedule(stamps, cameras, rate_hz):
        first_sent.setdefault(stamp, int(t * 1e9))
        for c in cams:
            at = int((t + (delivery_ms + rng.exponential(jitter_ms)) / 1e3) * 1e9)
            last[c] = at = max(at, last[c] + 1)  # one FIFO transport per camera
            arrivals.append((at, c, stamp))
    arrivals.sort()
    sync = ApproximateTimeSync(
        cameras, int(slop_s * 1e9), int(max_wait_s * 1e9), max_lag_ns=int(max_lag_s * 1e9)
    )
    out, k, now = [], 0, 0
    end = arrivals[-1][0] + int(2e9)
    while now <= end:
        while k < len(arrivals) and arrivals[k][0] <= now:
            at, c, stamp = arrivals[k]
            out += [(at, fs) for fs in sync.add(c, stamp, c, at)]
            k += 1
        out += [(now, fs) for fs in sync.poll(now)]
        now += int(poll_s * 1e9)
    emitted = {fs.stamp_ns: t for t, fs in out}
    lat = np.array([(emitted[s] - first_sent[s]) / 1e6 for s in stamps if s in emitted])
    missing = [c for _, fs in out for c in fs.missing]
    return {
        "frames": frames,
        "frames_without_set": sum(s not in emitted for s in stamps),
        "latency_ms_median": float(np.median(lat)),
        "latency_ms_p99": float(np.percentile(lat, 99)),
        "missing_slots": {c: missing.count(c) for c in sorted(set(missing))},
        "sync_timeouts": sync.stats.timeouts,
        "dropped": {r.value: n for r, n in sync.stats.dropped.items() if n},
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    add_params_argument(ap, "demo.yaml")
    ap.add_argument("--frames", type=int, default=150, help="scene frames to replay")
    ap.add_argument("--rate", type=float, default=30.0, help="publish rate, Hz")
    ap.add_argument("--difficulty", default=None, choices=("none", "easy", "medium", "hard"))
    ap.add_argument("--num-vertices", type=int, default=None, help="mesh vertices per person")
    ap.add_argument(
        "--max-rate", type=float, default=None, help="frontend max_rate, Hz (stamp-aligned decimation)"
    )
    ap.add_argument("--max-wait", type=float, default=None, help="association max_wait, s")
    add_fault_arguments(ap)
    ap.add_argument("--max-lag", type=float, default=None, help="association max_lag, s")
    ap.add_argument(
        "--sync-model",
        action="store_true",
        help="no processes: the synchroniser alone on the fault schedule, with a "
        "delivery model (see sync_model); isolates its decisions from CPU load",
    )
    ap.add_argument("--log-dir", type=Path, default=None, help="node logs (default: a temp dir)")
    add_json_argument(ap)
    a = ap.parse_args(argv)
    try:
        check_params_file(a.params)
    except ValueError as e:
        return fail(PROG, e)
    if a.sync_model:
        cams = load_rig_param(
            load_node_params(resolve_config_path(a.params), "association").get("rig", "")
        ).names
        report = sync_model(
            cams, a.frames, a.rate, faults_from(a), max_wait_s=a.max_wait or 0.15, max_lag_s=a.max_lag or 0.0
        )
        print_report(report, a.json)
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="maem_latency_"))
    fe: dict[str, Any] = {"frames": max(a.frames, 1)}
    if a.difficulty:
        fe["difficulty"] = a.difficulty
    if a.num_vertices:
        fe["num_vertices"] = a.num_vertices
    if a.max_rate:
        fe["max_rate"] = a.max_rate
    assoc = {k: v for k, v in (("max_wait", a.max_wait), ("max_lag", a.max_lag)) if v}
    params = write_params(a.params, tmp / "params.yaml", frontend=fe, association=assoc or None)
    report = run(params, a.frames, a.rate, a.log_dir or tmp / "logs", faults=faults_from(a))
    print_report(report, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
