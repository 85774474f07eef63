"""maem-soak: run the multi-process graph for minutes; report RSS per node and every drop.

    maem-soak --minutes 10 --rate 10            (python -m maem_ros.tools.bench.soak)

Starts the graph of tools/bench/latency.py (one synthetic frontend per camera, association,
triangulation as separate processes), publishes one tiny image per camera per scene frame at
``--rate`` Hz for ``--minutes`` (a scene that long, so stamps never go back) with optional
faults (``--lag-camera``, ``--stale-every``), samples each node's resident memory (VmRSS) every
``--sample`` s and listens to /maem/poses and /diagnostics.

Report: RSS per node at the start (after the first ``--warmup`` s), the end and its growth in
percent; frames published and with poses; per node its drops by reason; and the message
balance of every edge of the graph, from the nodes' own counters: what one stage published must
be received or counted lost (``dropped/dds_lost``) by the next, and what a node received must be
processed or dropped under a reason. ``unexplained`` is the sum of those imbalances (0 = every
frame that did not produce poses is accounted for). A soak is a tool, not a test.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from maem_ros.params import load_node_params
from maem_ros.ros.params import load_rig_param
from maem_ros.ros.probe import ReplayClient
from maem_ros.tools.bench.latency import (
    Faults,
    GraphProcesses,
    add_fault_arguments,
    faults_from,
    make_scene,
    write_params,
)
from maem_ros.tools.cli import add_json_argument, add_params_argument, check_params_file, fail, print_report


def rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (Linux /proc), NaN when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _n(d: Mapping[str, str], key: str) -> int:
    return int(float(d.get(key, "0")))


def balance(
    diags: Mapping[str, Mapping[str, str]], cameras: Sequence[str], images_sent: int, poses_received: int
) -> dict[str, int]:
    """Per edge / node: messages neither delivered nor counted (0 everywhere = all explained).

    images -> frontend: sent = received + dds_lost; frontend: received = processed + dropped
    (dds_lost excluded) + skipped by max_rate; frontends -> association: detections published
    (= frontend processed) = received + dds_lost; association: received = sets x cameras -
    missing slots + dropped messages; association -> triangulation: sets processed = received
    + dds_lost; triangulation: received = processed + dropped; -> us: processed = poses received.
    """
    out: dict[str, int] = {}
    assoc, tri = diags.get("/association", {}), diags.get("/triangulation", {})
    detections = 0
    for c in cameras:
        fe = diags.get(f"/{c}/frontend", {})
        topic = f"{c}/image_raw"
        lost = _n(fe, "dropped/dds_lost")
        out[f"images->{c}"] = images_sent - _n(fe, f"received/{topic}") - lost
        out[f"frontend {c}"] = (
            _n(fe, f"received/{topic}")
            - _n(fe, "frames_processed")
            - (_n(fe, "frames_dropped") - lost)
            - _n(fe, "count/skipped_max_rate")
        )
        detections += _n(fe, "frames_processed")
    received = sum(_n(assoc, f"received/{c}/detections") for c in cameras)
    assoc_lost = _n(assoc, "dropped/dds_lost")
    out["frontends->association"] = detections - received - assoc_lost
    per_set = ("dropped/association_error", "dropped/internal_error")
    set_drops = sum(_n(assoc, k) for k in per_set)
    msg_drops = _n(assoc, "frames_dropped") - assoc_lost - set_drops
    out["association"] = (
        received
        - len(cameras) * _n(assoc, "count/sync_sets")
        + sum(_n(assoc, f"missing/{c}") for c in cameras)
        - msg_drops
    )
    tri_lost = _n(tri, "dropped/dds_lost")
    out["association->triangulation"] = (
        _n(assoc, "frames_processed") - _n(tri, "received/maem/clusters") - tri_lost
    )
    out["triangulation"] = (
        _n(tri, "received/maem/clusters")
        - _n(tri, "frames_processed")
        - (_n(tri, "frames_dropped") - tri_lost)
    )
    out["triangulation->poses"] = _n(tri, "frames_processed") - poses_received
    return out


def run(
    params_file: Path,
    minutes: float,
    rate_hz: float,
    log_dir: Path,
    sample_s: float,
    warmup_s: float,
    faults: Faults,
    startup_timeout: float = 180.0,
) -> dict[str, Any]:
    rig = load_rig_param(load_node_params(params_file, "association").get("rig", ""))
    scene = make_scene(params_file)
    frames = min(scene.num_frames, int(round(minutes * 60 * rate_hz)))
    graph = GraphProcesses(params_file, rig.names, log_dir).start()
    try:
        client = ReplayClient(rig.names, name="maem_soak")
    except BaseException:
        graph.stop()
        raise
    samples: list[tuple[float, dict[str, float]]] = []
    try:
        if not client.wait_ready(startup_timeout, alive=lambda: not graph.dead()):
            raise RuntimeError(
                f"graph not ready (dead: {graph.dead()}; not matched: {client.unready()})\n{graph.logs()}"
            )
        stamps = [scene.stamp_ns(f) for f in range(frames)]
        t0 = next_sample = time.perf_counter()
        for offset, stamp, cams in faults.schedule(stamps, rig.names, rate_hz):
            target = t0 + offset
            while (now := time.perf_counter()) < target:
                if now >= next_sample:
                    samples.append((now - t0, {p.name: rss_mb(p.popen.pid) for p in graph.procs}))
                    next_sample += sample_s
                time.sleep(min(target - now, 0.005))
            client.publish_frame(stamp, cams)
            if graph.dead():
                raise RuntimeError(f"nodes died during the soak: {graph.dead()}\n{graph.logs()}")
        samples.append((time.perf_counter() - t0, {p.name: rss_mb(p.popen.pid) for p in graph.procs}))
        time.sleep(3.0)  # drain, then two more diagnostics periods
        time.sleep(2.5)
    finally:
        codes = graph.stop()
        client.close()
    with client.lock:
        poses, diags = dict(client.poses), dict(client.diagnostics)
    valid = set(stamps)
    start = next((s for t, s in samples if t >= warmup_s), samples[0][1])
    end = samples[-1][1]
    memory = {
        n: {
            "start_mb": round(start[n], 1),
            "end_mb": round(end[n], 1),
            "growth_percent": round(100 * (end[n] - start[n]) / start[n], 2),
        }
        for n in sorted(end)
    }
    drops = {n: {k: v for k, v in d.items() if k.startswith("dropped/")} for n, d in sorted(diags.items())}
    bal = balance(diags, rig.names, frames, sum(s in poses for s in valid))
    return {
        "minutes": round(samples[-1][0] / 60, 2),
        "rate_hz": rate_hz,
        "cameras": len(rig.names),
        "frames_published": frames,
        "frames_with_poses": sum(s in poses for s in valid),
        "rss": memory,
        "drops": drops,
        "balance": bal,
        "unexplained": int(sum(abs(v) for v in bal.values())),
        "exit_codes": codes,
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="maem-soak", description=__doc__.splitlines()[0])
    add_params_argument(ap, "demo.yaml")
    ap.add_argument("--minutes", type=float, default=10.0, help="soak duration (default 10)")
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second (default 10)")
    ap.add_argument(
        "--num-vertices",
        type=int,
        default=300,
        help="mesh vertices per person of the synthetic frontends (default 300)",
    )
    ap.add_argument("--sample", type=float, default=10.0, help="RSS sample period, s")
    ap.add_argument(
        "--warmup",
        type=float,
        default=30.0,
        help="RSS baseline taken this many s in (imports, kernels, first frames)",
    )
    add_fault_arguments(ap)
    ap.add_argument("--log-dir", type=Path, default=None, help="node logs (default: a temp dir)")
    add_json_argument(ap)
    a = ap.parse_args(argv)
    if not (a.minutes > 0 and a.rate > 0 and a.sample > 0):
        return fail("maem-soak", "--minutes, --rate and --sample must be > 0")
    try:
        check_params_file(a.params)
    except ValueError as e:
        return fail("maem-soak", e)
    tmp = Path(tempfile.mkdtemp(prefix="maem_soak_"))
    frames = int(round(a.minutes * 60 * a.rate)) + 1
    params = write_params(
        a.params,
        tmp / "params.yaml",
        frontend={"frames": frames, "num_vertices": a.num_vertices, "fps": a.rate},
    )
    report = run(
        params,
        a.minutes,
        a.rate,
        a.log_dir or tmp / "logs",
        a.sample,
        min(a.warmup, a.minutes * 30),
        faults_from(a),
    )
    print_report(report, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
