"""maem-bench --live: recorded full-mesh detections through association + triangulation at camera
rate, one publisher process per camera (as camera machines would); latency, drops, partial
sets, CPU per process and recall against ground truth.

    maem-bench --live                                # synthetic scene (config/demo.yaml), f32
    maem-bench --live --wire q4 --frames 150
    maem-bench --live --bag bags/demo --rate 30      # the bag's recorded /<cam>/detections
    maem-bench --live --vertex-stride 8              # a vertex subset, announced on the wire
    maem-bench --live --wire q4 --vertex-count 500   # 500 vertices spread over the mesh
    maem-bench --live --rate 60 --frames 600 --runs 5 --stress 5   # worst of 5, a CPU hog

Detections: from ``--bag`` (its /<cam>/detections and /maem/gt_poses), else regenerated from the
params file's synthetic scene (every publisher builds its camera's messages before the clock
starts, so generating them costs nothing during the run). Each camera's publisher process
(``python -m maem_ros.tools.bench.live --publish CAM``) sends frame f at T0 + f / rate (wall clock);
maem-association and maem-triangulation run as nodes with the params file. This process
subscribes /maem/poses: latency = arrival - scheduled publish time of that frame. Frames
without poses = published frames that never got a /maem/poses message. Partial sets = the
association's frame sets that missed a camera (its /diagnostics). Recall = ground-truth players
with a pose within 500 mm MPJPE (Hungarian), live and offline (core association +
triangulation on the same decoded messages in this process). Every process gets the shipped
Fast DDS profile (config/fastdds.xml) unless FASTRTPS_DEFAULT_PROFILES_FILE is set or
``--no-profile``. The nodes run with their live overload policy (stale frames skipped, counted
dropped/behind; ``accounting`` says whether every frame without poses was counted);
``--keep-every-set`` turns it off. ``--runs`` / ``--stress``: tools/bench/live_runs.py.
"""
from __future__ import annotations

import argparse
import os
import pickle
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: poses within this MPJPE (m) of a ground-truth player count as recalling it
RECALL_MM = 500.0


# ---------------------------------------------------------------------------------------------
# the messages: bag or synthetic scene
# ---------------------------------------------------------------------------------------------
def _encode(fd, wire_layout: str, stride: int, count: int = 0) -> bytes:
    from rclpy.serialization import serialize_message

    from maem_ros.ros import wire
    if stride > 1 or count > 0:
        fd = fd.with_vertex_subset(stride, count)
    return bytes(serialize_message(wire.detections_to_msg(fd, wire_layout)))


def camera_messages(camera: str, params_file: Path, bag: Path | None, frames: int,
                    wire_layout: str, stride: int, count: int = 0) -> list[tuple[int, bytes]]:
    """(stamp ns, serialized /<camera>/detections) per frame, in order."""
    if bag is not None:
        from maem_ros import bagio
        from maem_ros.ros import wire
        out: list[tuple[int, bytes]] = []
        for m in bagio.read_messages(bag, [f"/{camera}/detections"]):
            if len(out) >= frames:
                break
            fd = wire.msg_to_detections(m.decode(), m.topic)
            out.append((fd.stamp_ns, _encode(fd, wire_layout, stride, count)))
        if not out:
            raise ValueError(f"bag {str(bag)!r}: no /{camera}/detections")
        return out
    from maem_ros.tools.bench.latency import make_scene
    scene = make_scene(params_file)
    return [(scene.stamp_ns(f), _encode(scene.detections(camera, f), wire_layout, stride, count))
            for f in range(min(frames, scene.num_frames))]


def ground_truth(params_file: Path, bag: Path | None, stamps: Sequence[int]
                 ) -> dict[int, np.ndarray]:
    """stamp -> (P,13,3) world m ground-truth players (sportcenter_13, NaN = masked joint)."""
    from maem_ros.core.skeleton import SPORTCENTER_13
    if bag is not None:
        from maem_ros.tools.demo.demo_bag import load_bag
        return dict(load_bag(bag).gt)
    from maem_ros.tools.bench.latency import make_scene
    scene = make_scene(params_file)
    frame = {scene.stamp_ns(f): f for f in range(scene.num_frames)}
    return {s: SPORTCENTER_13.select(scene.gt_keypoints(frame[s])[scene.is_player])
            for s in stamps if s in frame}


# ---------------------------------------------------------------------------------------------
# one camera's publisher process
# ---------------------------------------------------------------------------------------------
def publish_main(a: argparse.Namespace) -> int:
    """Build the messages, wait until the association subscribes, write them to ``CAM.pkl``
    (for the offline comparison), signal READY, then publish on the shared start time.

    Signals as in a node (ros/cli.stop_on_signals): SIGINT/SIGTERM stop it between frames,
    SIGUSR1 dumps its stacks, and a teardown that stalls (DDS) ends the process
    SHUTDOWN_GRACE_S after it began, with the watchdog's line in the log (the report's
    forced_exits). rclpy's own signal handler is not installed, as in the nodes. The teardown
    detaches the DDS discovery listener first (ros/cli.shutdown_ros): without it, a Fast DDS
    deadlock left a publisher or node that did not exit in ~1 run in 35 here."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import PointCloud2

    from maem_ros.ros.cli import shutdown_ros, stop_on_signals
    from maem_ros.ros.common import DATA_QOS, keep_freed_memory, use_shipped_dds_profile
    from maem_ros.ros.frontend_node import HEAP_PREFAULT_MB

    stop = stop_on_signals(f"live_publisher_{a.publish}")
    keep_freed_memory(HEAP_PREFAULT_MB)  # as a frontend process does (run_node)
    msgs = camera_messages(a.publish, Path(a.params), a.bag, a.frames, a.wire, a.vertex_stride,
                           a.vertex_count)
    work = Path(a.work)
    with open(work / f"{a.publish}.pkl", "wb") as fh:
        pickle.dump(msgs, fh)
    if not a.no_profile:
        use_shipped_dds_profile()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"live_publisher_{a.publish}")
    pub = node.create_publisher(PointCloud2, f"/{a.publish}/detections", DATA_QOS)
    try:
        deadline = time.monotonic() + 120
        while (pub.get_subscription_count() == 0 and time.monotonic() < deadline
               and not stop.is_set()):
            time.sleep(0.05)
        (work / f"{a.publish}.ready").write_text("ready")
        start = work / "start"
        while not start.exists() and not stop.is_set():
            time.sleep(0.005)
        t0 = float(start.read_text()) if not stop.is_set() else 0.0
        for f, (_, data) in enumerate(msgs):
            target = t0 + f / a.rate
            while (now := time.time()) < target and not stop.is_set():
                time.sleep(min(target - now, 0.002))
            if stop.is_set():
                break
            pub.publish(data)
        else:
            print(f"published {len(msgs)} frames", flush=True)
            stop.wait(1.0)  # let reliable delivery finish before the writer goes away
    finally:
        stop.set()  # the teardown begins: the watchdog's grace from now
        shutdown_ros(node)
        print("done", flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------
def _listener():
    from sensor_msgs.msg import PointCloud2

    from maem_ros.ros import wire
    from maem_ros.ros.common import DATA_QOS
    from maem_ros.ros.probe import BackgroundNode

    bg = BackgroundNode("maem_live_listener")
    bg.poses = {}

    def on_poses(msg):
        t = time.time()
        pf = wire.msg_to_poses(msg, "/maem/poses")
        with bg.lock:
            bg.poses.setdefault(pf.stamp_ns, (t, pf))

    bg.subs = [bg.node.create_subscription(PointCloud2, "/maem/poses", on_poses, DATA_QOS)]
    bg.watch_diagnostics()
    return bg.start()


def _unready(listener, cameras: Sequence[str]) -> list[str]:
    """The links not yet matched at both ends: publishers -> association (the publishers wait
    for their end themselves) -> triangulation -> the listener."""
    from maem_ros.ros.probe import fusion_links, unmatched_links

    ours = [] if listener.subs[0].get_publisher_count() else ["/maem/poses -> listener"]
    return ours + unmatched_links(listener.diagnostics_snapshot(),
                                  fusion_links(cameras, image_topic=None))


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


def offline_poses(rig, params_file: Path, messages: dict[str, list[tuple[int, bytes]]]
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
    temporal = TemporalAssociator(rig, AssociationParams.from_mapping(assoc),
                                  TemporalParams.from_mapping(assoc))
    tp = TriangulationParams.from_mapping(tri)
    by_stamp: dict[int, dict] = {}
    for cam, msgs in messages.items():
        for stamp, data in msgs:
            by_stamp.setdefault(stamp, {})[cam] = wire.msg_to_detections(
                wire.cdr_to_cloud(data, f"/{cam}/detections"), f"/{cam}/detections")
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


def _ros_env(env: dict[str, str]) -> list[str]:
    """NAME=value of the variables the publishers need (``ip netns exec`` keeps the environment,
    spelled out so a sudo wrapper cannot drop them)."""
    keys = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS",
            "FASTRTPS_DEFAULT_PROFILES_FILE", "PYTHONUNBUFFERED", "OMP_NUM_THREADS", "PATH")
    return [f"{k}={env[k]}" for k in keys if k in env]


def run_live(a: argparse.Namespace) -> dict[str, Any]:
    """Run the live benchmark in a fresh work folder, removed afterwards: it holds every
    camera's messages (3 GB for 300 full-mesh frames); a failure's error carries the logs."""
    work = Path(tempfile.mkdtemp(prefix="maem_live_"))
    try:
        return _run_live(a, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _run_live(a: argparse.Namespace, work: Path) -> dict[str, Any]:
    from maem_ros.params import load_node_params
    from maem_ros.ros.common import DDS_PROFILE_VARS, load_rig_param, use_shipped_dds_profile
    from maem_ros.tools.bench.latency import write_params
    from maem_ros.tools.bench.live_runs import accounting, hog_window, start_hog, stress_figures
    from maem_ros.tools.processes import ProcessGroup, module_command, node_command

    policy = {**({"max_backlog": a.max_backlog} if a.max_backlog is not None else {}),
              **({"keep_every_set": True} if a.keep_every_set else {})}
    assoc_over = {**({"max_wait": a.max_wait} if a.max_wait else {}), **policy} or None
    params = write_params(a.params, work / "params.yaml",
                          frontend={"frames": max(a.frames, 1), "num_vertices": a.vertices},
                          association=assoc_over, triangulation=policy or None)
    if a.bag is not None:
        from maem_ros import bagio
        rig_yaml = bagio.read_rig_yaml(a.bag)
        if rig_yaml:
            (work / "rig.yaml").write_text(rig_yaml)
            params = write_params(params, work / "params.yaml",
                                  association={"rig": str(work / "rig.yaml")},
                                  triangulation={"rig": str(work / "rig.yaml")})
    rig = load_rig_param(load_node_params(params, "association").get("rig", ""))
    profile = None if a.no_profile else use_shipped_dds_profile()
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    if a.no_profile:
        for v in DDS_PROFILE_VARS:
            env.pop(v, None)
    group = ProcessGroup(work / "logs", env)
    listener = hog = None
    try:
        for kind in ("association", "triangulation"):
            group.start(kind, node_command(kind, params))
        for cam in rig.names:
            cmd = module_command("maem_ros.tools.bench.live", "--publish", cam, "--params", str(params),
                                 "--work", str(work), "--frames", str(a.frames), "--rate",
                                 f"{a.rate}", "--wire", a.wire, "--vertex-stride",
                                 str(a.vertex_stride), "--vertex-count", str(a.vertex_count))
            cmd += (["--bag", str(a.bag)] if a.bag else []) + (["--no-profile"] if a.no_profile
                                                                else [])
            if a.publisher_netns:  # the camera machines: another network namespace
                cmd = ["ip", "netns", "exec", a.publisher_netns, "env", *_ros_env(env), *cmd]
            group.start(f"publisher_{cam}", cmd)
        listener = _listener()
        deadline = time.monotonic() + a.startup_timeout
        while not all((work / f"{c}.ready").exists() for c in rig.names):
            if group.dead():
                raise RuntimeError(f"process exited during start-up: {group.dead()}\n"
                                   f"{group.logs()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"publishers not ready after {a.startup_timeout:.0f} s\n"
                                   f"{group.logs()}")
            time.sleep(0.1)
        while unready := _unready(listener, rig.names):
            if time.monotonic() > deadline:
                raise RuntimeError(f"graph not matched after {a.startup_timeout:.0f} s: {unready}"
                                   f"\n{group.logs()}")
            time.sleep(0.05)
        messages = {c: pickle.loads((work / f"{c}.pkl").read_bytes()) for c in rig.names}
        stamps = [s for s, _ in messages[rig.names[0]]]
        procs = list(group.procs.values())
        cpu0 = {p.name: p.cpu_seconds() for p in procs}
        t0 = time.time() + 0.5
        if a.stress:
            hog_at = hog_window(t0, len(stamps), a.rate, a.stress)
            hog = start_hog(hog_at[0], a.stress)
        (work / "start.tmp").write_text(repr(t0))
        (work / "start.tmp").rename(work / "start")  # atomic: a publisher never reads it half
        end = t0 + len(stamps) / a.rate
        while time.time() < end + a.drain and not (time.time() > end and stamps[-1] in
                                                   listener.poses):
            failed = {n: c for n, c in group.dead().items() if c != 0}
            if failed:
                raise RuntimeError(f"process failed during the run: {failed}\n{group.logs()}")
            time.sleep(0.05)
        wall = time.time() - t0
        cpu1 = {p.name: p.cpu_seconds() for p in procs}
        time.sleep(1.2)  # one more /diagnostics period
        with listener.lock:
            poses = dict(listener.poses)
            diags = dict(listener.diagnostics)
    finally:
        publishers = [n for n in group.procs if n.startswith("publisher_")]
        stop_by = time.monotonic() + 10.0  # they exit by themselves after the last frame
        while time.monotonic() < stop_by and len(group.dead(publishers)) < len(publishers):
            time.sleep(0.05)
        codes = group.stop(timeout_s=15.0)
        forced = group.forced_exits()
        if failed_names := [n for n, c in codes.items() if c != 0]:
            # the work folder and its logs go when the run ends: say here why they failed
            print(f"maem-bench --live: exit codes {codes}\n{group.logs(names=failed_names)}",
                  file=sys.stderr)
        if listener is not None:
            listener.close()
        if hog is not None and hog.poll() is None:
            hog.kill()
    sent = {s: t0 + f / a.rate for f, s in enumerate(stamps)}
    lat_by_frame = {f: (poses[s][0] - sent[s]) * 1e3 for f, s in enumerate(stamps) if s in poses}
    lat = np.array(list(lat_by_frame.values()))
    gt = ground_truth(params, a.bag, stamps)
    from maem_ros.core.skeleton import SPORTCENTER_13, convert
    live = {s: convert(p.joints, SPORTCENTER_13) for s, (_, p) in poses.items()}
    assoc: dict[str, str] = next(
        (kv for n, kv in diags.items() if n.strip("/").endswith("association")), {})
    tri: dict[str, str] = next(
        (kv for n, kv in diags.items() if n.strip("/").endswith("triangulation")), {})
    size = np.median([len(d) for m in messages.values() for _, d in m])
    received = sum(int(v) for k, v in assoc.items()
                   if k.startswith("received/") and k.endswith("/detections"))
    report = {
        "cameras": len(rig), "frames_published": len(stamps), "rate_hz": a.rate,
        "wire": a.wire, "vertex_stride": a.vertex_stride, "vertex_count": a.vertex_count,
        "max_backlog_s": a.max_backlog or 0.0,  # 0: the nodes' automatic bound
        "keep_every_set": bool(a.keep_every_set),
        "publisher_netns": a.publisher_netns,
        "message_mb": round(float(size) / 1e6, 3),
        "link_mbit_s": round(float(size) * len(rig) * a.rate * 8 / 1e6, 1),
        # what reached the association: messages taken (counted before decoding) of those sent
        "messages_sent": len(stamps) * len(rig),
        "messages_received": received,
        "received_mbit_s": round(received * float(size) * 8 / 1e6 / max(wall, 1e-9), 1),
        "dds_profile": profile or os.environ.get(DDS_PROFILE_VARS[0]) or "Fast DDS default",
        "load_average_1min": round(os.getloadavg()[0], 2),
        "latency_ms_median": float(np.median(lat)) if len(lat) else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
        "latency_ms_max": float(lat.max()) if len(lat) else None,
        # where the tail is: (frame index, ms) of the five slowest frames
        "slowest_frames": [(f, round(ms, 1)) for f, ms in
                           sorted(lat_by_frame.items(), key=lambda e: -e[1])[:5]],
        # every frame's latency in publish order (None: no poses): where a stall starts and
        # whether the node recovers from it
        "latency_ms_by_frame": [round(lat_by_frame[f], 1) if f in lat_by_frame else None
                                for f in range(len(stamps))],
        "frames_without_poses": int(sum(s not in poses for s in stamps)),
        "partial_sets": int(float(assoc.get("count/sync_partial_sets", 0))),
        # where they happen: frames whose best-seen person has fewer views than the run's best
        "frames_with_fewer_views": _fewer_views(poses, stamps),
        "missing_camera_counts": {k.split("/", 1)[1]: int(v) for k, v in assoc.items()
                                  if k.startswith("missing/")},
        "association_dropped": {k: v for k, v in assoc.items() if k.startswith("dropped/")},
        "triangulation_dropped": {k: v for k, v in tri.items() if k.startswith("dropped/")},
        # every frame without poses counted by a node? (live_runs.accounting)
        "accounting": accounting(len(stamps), int(sum(s not in poses for s in stamps)),
                                 len(rig), assoc, tri),
        # the longest time a node was behind (skipping, or working on stale frames), s
        "behind_longest_s": max(float(kv.get("behind/longest_s", 0)) for kv in (assoc, tri)),
        "association_ms_median": float(assoc.get("time_ms/associate/median", "nan")),
        "association_stage_ms_median": _stage_medians(assoc),
        "triangulation_stage_ms_median": _stage_medians(tri),
        "association_stage_ms_p99": _stage_medians(assoc, "p99"),
        "triangulation_stage_ms_p99": _stage_medians(tri, "p99"),
        "recall_live": recall(live, gt, stamps),
        "recall_offline": recall(offline_poses(rig, params, messages), gt, stamps),
        "cpu_percent": {n: round(100 * (cpu1[n] - cpu0[n]) / wall, 1) for n in cpu0},
        # CPU time per published frame: what a process needs of one core at this rate (< 1000 /
        # rate ms to keep up), less dependent on what else loads the machine than the latency
        "cpu_ms_per_frame": {n: round(1e3 * (cpu1[n] - cpu0[n]) / len(stamps), 2) for n in cpu0},
        "exit_codes": codes,
        # processes whose shutdown watchdog ended a stalled teardown (exit code 0; 1 from its
        # backstop when the stall held the GIL)
        "forced_exits": forced,
    }
    if a.stress:
        report["stress"] = stress_figures(report["latency_ms_by_frame"], a.rate,
                                          hog_at[0] - t0, hog_at[1] - t0)
    return report


def _stage_medians(diagnostics: dict[str, str], stat: str = "median") -> dict[str, float]:
    """stage -> ms from a node's /diagnostics (``time_ms/<stage>/<stat>``, median or p99)."""
    return {k.split("/")[1]: float(v) for k, v in diagnostics.items()
            if k.startswith("time_ms/") and k.endswith(f"/{stat}")}


def _fewer_views(poses: dict[int, Any], stamps: Sequence[int]) -> list[int]:
    """Frame indices whose poses have at most (the run's most views - 1) views: a camera was
    missing from that frame set (or lost every person there)."""
    best = {f: int(poses[s][1].views.max(initial=0)) for f, s in enumerate(stamps) if s in poses}
    top = max(best.values(), default=0)
    return [f for f, v in best.items() if v < top]


def add_live_arguments(p: argparse.ArgumentParser) -> None:
    """The --live options of maem-bench (--frames, --wire, --vertices, --params are shared)."""
    g = p.add_argument_group("live benchmark (--live)")
    g.add_argument("--live", action="store_true",
                   help="publish detections at camera rate through the node graph (see above)")
    g.add_argument("--bag", type=Path, default=None,
                   help="--live: publish this bag's recorded /<cam>/detections")
    g.add_argument("--rate", type=float, default=30.0, help="--live: frames per second")
    g.add_argument("--vertex-stride", type=int, default=1,
                   help="--live: send every n-th vertex (announced subset)")
    g.add_argument("--vertex-count", type=int, default=0,
                   help="--live: send this many of those vertices, spread evenly (announced "
                        "subset; 0 = all)")
    g.add_argument("--max-wait", type=float, default=None, help="--live: association max_wait, s")
    g.add_argument("--max-backlog", type=float, default=None,
                   help="--live: the nodes' max_backlog, s (skip frames that waited that long "
                        "for the node; default: their automatic bound, 4 frame periods)")
    g.add_argument("--keep-every-set", action="store_true",
                   help="--live: the nodes process every frame however far behind (what a "
                        "replay wanting every frame sets; the live default skips stale ones)")
    from maem_ros.tools.bench.live_runs import add_arguments as add_runs_arguments
    add_runs_arguments(g)
    g.add_argument("--drain", type=float, default=3.0,
                   help="--live: seconds to wait for the last poses")
    g.add_argument("--startup-timeout", type=float, default=180.0,
                   help="--live: seconds for publishers to build messages and match")
    g.add_argument("--no-profile", action="store_true",
                   help="--live: Fast DDS defaults instead of config/fastdds.xml")
    g.add_argument("--publisher-netns", default=None, metavar="NS",
                   help="--live: run the camera publishers in network namespace NS (ip netns; "
                        "root), as separate machines (see scripts/netns_link.sh)")


def check_live_arguments(a: argparse.Namespace) -> None:
    if not a.rate > 0:
        raise ValueError(f"--rate: must be > 0, got {a.rate}")
    if a.vertex_stride < 1:
        raise ValueError(f"--vertex-stride: must be >= 1, got {a.vertex_stride}")
    if a.max_backlog is not None and a.max_backlog < 0:
        raise ValueError(f"--max-backlog: must be >= 0, got {a.max_backlog}")
    if a.vertex_count < 0:
        raise ValueError(f"--vertex-count: must be >= 0, got {a.vertex_count}")
    if a.bag is not None and not Path(a.bag).exists():
        raise ValueError(f"--bag: {str(a.bag)!r} does not exist")
    from maem_ros.tools.bench.live_runs import check_arguments as check_runs_arguments
    check_runs_arguments(a)


def _publisher_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m maem_ros.tools.bench.live")
    p.add_argument("--publish", required=True, help="camera name")
    p.add_argument("--params", required=True)
    p.add_argument("--work", required=True)
    p.add_argument("--frames", type=int, required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--wire", default="f32", choices=("f32", "q4"))
    p.add_argument("--vertex-stride", type=int, default=1)
    p.add_argument("--vertex-count", type=int, default=0)
    p.add_argument("--bag", type=Path, default=None)
    p.add_argument("--no-profile", action="store_true")
    return p


if __name__ == "__main__":
    sys.exit(publish_main(_publisher_parser().parse_args()))
