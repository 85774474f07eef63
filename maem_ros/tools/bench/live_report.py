"""The figures of one maem-bench --live run (tools/bench/live.py): latency (poses arrival -
scheduled publish time of the frame, ms), frames without poses, the nodes' /diagnostics (partial
sets, drops, lag, stage times), CPU per process, and recall against ground truth, live and
offline (the nodes' pipeline on the same messages in this process)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: poses within this MPJPE (m) of a ground-truth player count as recalling it
RECALL_MM = 500.0


def ground_truth(params_file: Path, bag: Path | None, stamps: Sequence[int]) -> dict[int, np.ndarray]:
    """stamp -> (P,13,3) world m ground-truth players (sportcenter_13, NaN = masked joint)."""
    from maem_ros.core.skeleton import SPORTCENTER_13

    if bag is not None:
        from maem_ros.tools.demo.demo_bag import load_bag

        return dict(load_bag(bag).gt)
    from maem_ros.tools.bench.latency import make_scene

    scene = make_scene(params_file)
    frame = {scene.stamp_ns(f): f for f in range(scene.num_frames)}
    return {
        s: SPORTCENTER_13.select(scene.gt_keypoints(frame[s])[scene.is_player]) for s in stamps if s in frame
    }


def recall(poses: dict[int, Any], gt: dict[int, np.ndarray], stamps: Sequence[int]) -> float:
    """Fraction of ground-truth players of ``stamps`` with a pose within RECALL_MM."""
    from maem_ros.tools.bench.latency import match_mpjpe

    hit = total = 0
    for s in stamps:
        want = gt.get(s)
        if want is None:
            continue
        total += len(want)
        if s in poses:
            hit += len(match_mpjpe(poses[s], want, RECALL_MM / 1e3)[0])
    return hit / total if total else float("nan")


def offline_poses(
    rig, params_file: Path, messages: dict[str, list[tuple[int, bytes]]]
) -> dict[int, np.ndarray]:
    """The nodes' pipeline on the same messages in this process, every frame set complete
    (the reference recall): the association node's TemporalAssociator (track-assisted or the
    per-frame pipeline, as ``params_file`` says), triangulation, and the triangulation node's
    ``publish_tentative`` rule; stamp -> (P,13,3) world m."""
    from maem_ros.core.association import AssociationParams
    from maem_ros.core.skeleton import SPORTCENTER_13, convert
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    from maem_ros.core.triangulation.ransac import TriangulationParams, triangulate
    from maem_ros.params import load_node_params
    from maem_ros.ros import wire
    from maem_ros.ros.triangulation_node import PARAMS as TRIANGULATION_PARAMS

    assoc = load_node_params(params_file, "association")
    tri = {s.name: s.default for s in TRIANGULATION_PARAMS}
    tri.update(load_node_params(params_file, "triangulation"))
    temporal = TemporalAssociator(
        rig, AssociationParams.from_mapping(assoc), TemporalParams.from_mapping(assoc)
    )
    tp = TriangulationParams.from_mapping(tri)
    by_stamp: dict[int, dict] = {}
    for cam, msgs in messages.items():
        for stamp, data in msgs:
            by_stamp.setdefault(stamp, {})[cam] = wire.msg_to_detections(
                wire.cdr_to_cloud(data, f"/{cam}/detections"), f"/{cam}/detections"
            )
    out = {}
    for stamp, frames in sorted(by_stamp.items()):
        res = temporal.step(frames, stamp)
        keep = np.ones(len(res.clusters), bool)
        if temporal.tp.temporal and not tri["publish_tentative"]:
            keep = np.asarray(res.track_ids) >= 0
        clusters = [c for c, k in zip(res.clusters, keep) if k]
        joints = np.asarray(triangulate(rig, frames, clusters, tp).joints, np.float64)
        out[stamp] = convert(joints, SPORTCENTER_13) if len(joints) else np.zeros((0, 13, 3))
    return out


@dataclass
class Observed:
    """What one timed run saw: the published stamps and messages, wall clock t0 (s) of frame
    0, run time (s), each process's CPU seconds before and after, the poses received
    (stamp -> (arrival s, Poses)), the last /diagnostics per node, exit codes."""

    stamps: list[int]
    messages: dict[str, list[tuple[int, bytes]]]
    t0: float
    wall: float
    cpu0: dict[str, float]
    cpu1: dict[str, float]
    poses: dict[int, Any]
    diags: dict[str, dict[str, str]]
    hog_at: tuple[float, float] | None
    codes: dict[str, int | None] = field(default_factory=dict)
    forced: Any = None
    clusters: dict[int, float] = field(default_factory=dict)  # stamp -> /maem/clusters arrival
    # camera -> s each publish returned after its frame's scheduled time, in frame order
    publisher_late_s: dict[str, list[float]] = field(default_factory=dict)
    # share of the machine's CPU time the hypervisor gave other guests during the run (%, from
    # /proc/stat; None where unknown): a run starved from outside shows it here
    cpu_steal_pct: float | None = None


def cpu_times() -> tuple[int, int] | None:
    """(steal, total) CPU time of the machine so far (jiffies, /proc/stat; None where there
    is no such file)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return None
    ticks = [int(x) for x in fields[:8]]  # user nice system idle iowait irq softirq steal
    return (ticks[7], sum(ticks)) if len(ticks) == 8 else None


def steal_pct(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """Steal time between two :func:`cpu_times` readings, % of all CPU time."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return round(100.0 * (after[0] - before[0]) / (after[1] - before[1]), 2)


#: the reference recall of the messages of a run, by what makes them: every run of one
#: ``maem-bench --live --runs N`` plays the same messages, so it is computed once
_OFFLINE_RECALL: dict[tuple, float] = {}


def _offline_recall(
    a: argparse.Namespace,
    params: Path,
    rig,
    messages: dict[str, list[tuple[int, bytes]]],
    gt,
    stamps: Sequence[int],
) -> float:
    """recall() of offline_poses() on ``messages``, cached by the params file's text, the
    layout options, the bag and the stamps."""
    key = (params.read_text(), a.wire, a.vertex_stride, a.vertex_count, str(a.bag), tuple(stamps))
    if key not in _OFFLINE_RECALL:
        _OFFLINE_RECALL[key] = recall(offline_poses(rig, params, messages), gt, stamps)
    return _OFFLINE_RECALL[key]


def live_report(
    a: argparse.Namespace, params: Path, rig, profile: str | None, run: Observed
) -> dict[str, Any]:
    """The run's figures (the JSON maem-bench --live prints)."""
    from maem_ros.core.skeleton import SPORTCENTER_13, convert
    from maem_ros.ros.process import DDS_PROFILE_VARS
    from maem_ros.tools.bench.live_runs import stress_figures

    stamps, poses, messages = run.stamps, run.poses, run.messages
    gt = ground_truth(params, a.bag, stamps)
    live = {s: convert(p.joints, SPORTCENTER_13) for s, (_, p) in poses.items()}
    assoc: dict[str, str] = next(
        (kv for n, kv in run.diags.items() if n.strip("/").endswith("association")), {}
    )
    tri: dict[str, str] = next(
        (kv for n, kv in run.diags.items() if n.strip("/").endswith("triangulation")), {}
    )
    size = np.median([len(d) for m in messages.values() for _, d in m])
    received = sum(
        int(v) for k, v in assoc.items() if k.startswith("received/") and k.endswith("/detections")
    )
    report = {
        "cameras": len(rig),
        "frames_published": len(stamps),
        "rate_hz": a.rate,
        "wire": a.wire,
        "vertex_stride": a.vertex_stride,
        "vertex_count": a.vertex_count,
        "max_backlog_s": a.max_backlog or 0.0,  # 0: the nodes' automatic bound
        "keep_every_set": bool(a.keep_every_set),
        "catch_up": a.catch_up or "newest",
        "publisher_netns": a.publisher_netns,
        "message_mb": round(float(size) / 1e6, 3),
        "link_mbit_s": round(float(size) * len(rig) * a.rate * 8 / 1e6, 1),
        # what reached the association: messages taken (counted before decoding) of those sent
        "messages_sent": len(stamps) * len(rig),
        "messages_received": received,
        "received_mbit_s": round(received * float(size) * 8 / 1e6 / max(run.wall, 1e-9), 1),
        "dds_profile": profile or os.environ.get(DDS_PROFILE_VARS[0]) or "Fast DDS default",
        "load_average_1min": round(os.getloadavg()[0], 2),
        **latency_figures(run, a.rate),
        **node_figures(assoc, tri, run, len(rig)),
        "recall_live": recall(live, gt, stamps),
        "recall_offline": _offline_recall(a, params, rig, messages, gt, stamps),
        "cpu_percent": {n: round(100 * (run.cpu1[n] - run.cpu0[n]) / run.wall, 1) for n in run.cpu0},
        # CPU time per published frame: what a process needs of one core at this rate (< 1000 /
        # rate ms to keep up), less dependent on what else loads the machine than the latency
        "cpu_ms_per_frame": {n: round(1e3 * (run.cpu1[n] - run.cpu0[n]) / len(stamps), 2) for n in run.cpu0},
        "exit_codes": run.codes,
        # processes whose shutdown watchdog ended a stalled teardown (exit code 0; 1 from its
        # backstop when the stall held the GIL)
        "forced_exits": run.forced,
    }
    if a.stress:
        assert run.hog_at is not None  # started with --stress
        report["stress"] = stress_figures(
            report["latency_ms_by_frame"], a.rate, run.hog_at[0] - run.t0, run.hog_at[1] - run.t0
        )
    return report


def latency_figures(run: Observed, rate: float) -> dict[str, Any]:
    """Latency (ms, poses arrival - scheduled publish time of that frame) and frames without
    poses."""
    stamps, poses = run.stamps, run.poses
    sent = {s: run.t0 + f / rate for f, s in enumerate(stamps)}
    lat_by_frame = {f: (poses[s][0] - sent[s]) * 1e3 for f, s in enumerate(stamps) if s in poses}
    lat = np.array(list(lat_by_frame.values()))
    assoc_hop = [round((run.clusters[s] - sent[s]) * 1e3, 1) if s in run.clusters else None for s in stamps]
    every_late = [x for lates in run.publisher_late_s.values() for x in lates]
    # each frame's latest publish over the cameras (a camera that stopped early counts no more)
    late = [
        max(lates[f] for lates in run.publisher_late_s.values() if f < len(lates))
        for f in range(max((len(x) for x in run.publisher_late_s.values()), default=0))
    ]
    return {
        "latency_ms_median": float(np.median(lat)) if len(lat) else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
        "latency_ms_max": float(lat.max()) if len(lat) else None,
        # where the tail is, the five slowest frames: (frame index, latency ms, the association's
        # hop ms (None: no clusters), the latest camera's publish ms after schedule): which
        # node, or the publishers, a slow frame waited for
        "slowest_frames": [
            (f, round(ms, 1), assoc_hop[f], round(late[f] * 1e3, 1) if f < len(late) else None)
            for f, ms in sorted(lat_by_frame.items(), key=lambda e: -e[1])[:5]
        ],
        # every frame's latency in publish order (None: no poses): where a stall starts and
        # whether the node recovers from it
        "latency_ms_by_frame": [
            round(lat_by_frame[f], 1) if f in lat_by_frame else None for f in range(len(stamps))
        ],
        "frames_without_poses": int(sum(s not in poses for s in stamps)),
        # of them, in the stream's first second: the nodes' start (tracks to build, the graph
        # starting together) apart from the steady state
        "frames_without_poses_first_s": int(sum(s not in poses for s in stamps[: max(int(rate), 1)])),
        # each frame's association hop (publish -> /maem/clusters; None: no clusters): which
        # node a slow frame waited for
        "association_hop_ms_by_frame": assoc_hop,
        # where the latency is: publish -> /maem/clusters (the association's hop) and
        # /maem/clusters -> /maem/poses (triangulation's), medians over frames with poses
        "association_hop_ms_median": _median_ms(
            [run.clusters[s] - sent[s] for s in stamps if s in run.clusters]
        ),
        "triangulation_hop_ms_median": _median_ms(
            [poses[s][0] - run.clusters[s] for s in stamps if s in poses and s in run.clusters]
        ),
        # how late the camera publishers sent (their publish returned after the schedule): a
        # machine too loaded for its publishers delays every frame before any node sees it
        # each frame's latest publish over the cameras, ms after its schedule, in publish
        # order: whether a slow start (or a hiccup) began before any node saw the frame
        "publisher_late_ms_by_frame": [round(x * 1e3, 1) for x in late],
        "publisher_late_ms_median": _median_ms(every_late),
        "publisher_late_ms_p99": (
            round(float(np.percentile(every_late, 99)) * 1e3, 1) if every_late else None
        ),
        "cpu_steal_pct": run.cpu_steal_pct,
    }


def _median_ms(seconds: list[float]) -> float | None:
    return round(float(np.median(seconds)) * 1e3, 1) if seconds else None


def node_figures(assoc: dict[str, str], tri: dict[str, str], run: Observed, cameras: int) -> dict[str, Any]:
    """What the nodes' /diagnostics say: partial sets, drops, lag, stage times (ms)."""
    from maem_ros.tools.bench.live_runs import accounting

    stamps, poses = run.stamps, run.poses
    return {
        "partial_sets": int(float(assoc.get("count/sync_partial_sets", 0))),
        # where they happen: frames whose best-seen person has fewer views than the run's best
        "frames_with_fewer_views": _fewer_views(poses, stamps),
        "missing_camera_counts": {
            k.split("/", 1)[1]: int(v) for k, v in assoc.items() if k.startswith("missing/")
        },
        "association_dropped": {k: v for k, v in assoc.items() if k.startswith("dropped/")},
        "triangulation_dropped": {k: v for k, v in tri.items() if k.startswith("dropped/")},
        # every frame without poses counted by a node? (live_runs.accounting)
        "accounting": accounting(len(stamps), int(sum(s not in poses for s in stamps)), cameras, assoc, tri),
        # the longest time a node was behind (skipping, or working on stale frames), s
        "behind_longest_s": max(float(kv.get("behind/longest_s", 0)) for kv in (assoc, tri)),
        # how the association worked: frame sets processed, of them light steps (late sets) and
        # light steps that left new people for a later set (core/tracking/temporal.py)
        "association_sets": int(float(assoc.get("frames_processed", 0))),
        "association_light_steps": int(float(assoc.get("count/light_steps", 0))),
        "association_new_deferred": int(float(assoc.get("count/new_deferred", 0))),
        "association_ms_median": float(assoc.get("time_ms/associate/median", "nan")),
        "association_stage_ms_median": _stage_medians(assoc),
        "triangulation_stage_ms_median": _stage_medians(tri),
        "association_stage_ms_p99": _stage_medians(assoc, "p99"),
        "triangulation_stage_ms_p99": _stage_medians(tri, "p99"),
    }


def _stage_medians(diagnostics: dict[str, str], stat: str = "median") -> dict[str, float]:
    """stage -> ms from a node's /diagnostics (``time_ms/<stage>/<stat>``, median or p99)."""
    return {
        k.split("/")[1]: float(v)
        for k, v in diagnostics.items()
        if k.startswith("time_ms/") and k.endswith(f"/{stat}")
    }


def _fewer_views(poses: dict[int, Any], stamps: Sequence[int]) -> list[int]:
    """Frame indices whose poses have at most (the run's most views - 1) views: a camera was
    missing from that frame set (or lost every person there)."""
    best = {f: int(poses[s][1].views.max(initial=0)) for f, s in enumerate(stamps) if s in poses}
    top = max(best.values(), default=0)
    return [f for f, v in best.items() if v < top]
