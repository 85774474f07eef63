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
params file's synthetic scene, simulated at ``--rate`` (stamps 1/rate apart, as a camera at
that rate stamps them; every publisher builds its camera's messages before the clock starts, so
generating them costs nothing during the run). Each camera's publisher process
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
``--keep-every-set`` turns it off. ``--runs`` / ``--stress``: tools/bench/live_runs.py. The
report's figures: tools/bench/live_report.py.
"""

from __future__ import annotations

import argparse
import atexit
import hashlib
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from maem_ros.tools.bench.live_report import Observed, cpu_times, live_report, steal_pct


# ---------------------------------------------------------------------------------------------
# the messages: bag or synthetic scene
# ---------------------------------------------------------------------------------------------
def _encode(fd, wire_layout: str, stride: int, count: int = 0) -> bytes:
    from rclpy.serialization import serialize_message

    from maem_ros.ros import wire

    if stride > 1 or count > 0:
        fd = fd.with_vertex_subset(stride, count)
    return bytes(serialize_message(wire.detections_to_msg(fd, wire_layout)))


def camera_messages(
    camera: str,
    params_file: Path,
    bag: Path | None,
    frames: int,
    wire_layout: str,
    stride: int,
    count: int = 0,
) -> list[tuple[int, bytes]]:
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
    return [
        (scene.stamp_ns(f), _encode(scene.detections(camera, f), wire_layout, stride, count))
        for f in range(min(frames, scene.num_frames))
    ]


#: where the publishers keep their messages (KEY/CAM.pkl) for every run of this process: the
#: runs of ``--runs N`` play the same messages, and building them is most of a run's start-up
_MESSAGES_DIR: list[Path] = []


def messages_dir(a: argparse.Namespace) -> Path:
    """The folder of the messages ``a`` makes (its options that shape them as the key), in a
    folder of this process made on first use and removed at exit."""
    if not _MESSAGES_DIR:
        _MESSAGES_DIR.append(Path(tempfile.mkdtemp(prefix="maem_live_messages_")))
        atexit.register(shutil.rmtree, _MESSAGES_DIR[0], ignore_errors=True)
    params = Path(a.params) if a.params else None
    key = repr(
        (
            params.read_text() if params and params.is_file() else str(params),
            a.frames,
            a.vertices,
            a.wire,
            a.vertex_stride,
            a.vertex_count,
            str(a.bag),
        )
    )
    out = _MESSAGES_DIR[0] / hashlib.sha1(key.encode()).hexdigest()[:16]
    out.mkdir(exist_ok=True)
    return out


def _load_or_build(a: argparse.Namespace) -> list[tuple[int, bytes]]:
    """The camera's messages from MESSAGES/CAM.pkl, or built (camera_messages) and written
    there (renamed into place once complete: a run stopped while writing leaves nothing)."""
    path = Path(a.messages) / f"{a.publish}.pkl"
    if path.exists():
        loaded: list[tuple[int, bytes]] = pickle.loads(path.read_bytes())
        return loaded
    msgs = camera_messages(
        a.publish, Path(a.params), a.bag, a.frames, a.wire, a.vertex_stride, a.vertex_count
    )
    part = path.with_suffix(".part")
    with open(part, "wb") as fh:
        pickle.dump(msgs, fh)
    part.rename(path)
    return msgs


# ---------------------------------------------------------------------------------------------
# one camera's publisher process
# ---------------------------------------------------------------------------------------------
def publish_main(a: argparse.Namespace) -> int:
    """Build the messages (or load them from ``--messages``/CAM.pkl, where the first of
    several runs wrote them for the offline comparison), wait until the association subscribes,
    signal READY, then publish on the shared start time.

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
    from maem_ros.ros.frontend_node import HEAP_PREFAULT_MB
    from maem_ros.ros.process import keep_freed_memory, use_shipped_dds_profile
    from maem_ros.ros.qos import DATA_QOS

    stop = stop_on_signals(f"live_publisher_{a.publish}")
    keep_freed_memory(HEAP_PREFAULT_MB)  # as a frontend process does (run_node)
    msgs = _load_or_build(a)
    work = Path(a.work)
    if not a.no_profile:
        use_shipped_dds_profile()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"live_publisher_{a.publish}")
    pub = node.create_publisher(PointCloud2, f"/{a.publish}/detections", DATA_QOS)
    try:
        deadline = time.monotonic() + 120
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline and not stop.is_set():
            time.sleep(0.05)
        (work / f"{a.publish}.ready").write_text("ready")
        start = work / "start"
        while not start.exists() and not stop.is_set():
            time.sleep(0.005)
        t0 = float(start.read_text()) if not stop.is_set() else 0.0
        late = []  # s each publish returned after its frame's scheduled time
        for f, (_, data) in enumerate(msgs):
            target = t0 + f / a.rate
            # one wake-up per frame, as a camera's: six publishers polling every few ms took
            # CPU from the nodes they stand in front of
            while (now := time.time()) < target and not stop.is_set():
                stop.wait(target - now)
            if stop.is_set():
                break
            pub.publish(data)
            late.append(time.time() - target)
        else:
            # how late this camera was: latency the nodes downstream cannot remove
            (work / f"{a.publish}.late.tmp").write_text(repr(late))
            (work / f"{a.publish}.late.tmp").rename(work / f"{a.publish}.late")
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
    from maem_ros.ros.probe import BackgroundNode
    from maem_ros.ros.qos import DATA_QOS

    bg = BackgroundNode("maem_live_listener")
    bg.poses = {}
    bg.clusters = {}  # stamp -> arrival (s): the association's hop, apart from triangulation's

    def on_clusters(msg):
        t = time.time()
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        with bg.lock:
            bg.clusters.setdefault(stamp, t)

    def on_poses(msg):
        t = time.time()
        pf = wire.msg_to_poses(msg, "/maem/poses")
        with bg.lock:
            bg.poses.setdefault(pf.stamp_ns, (t, pf))

    bg.subs = [
        bg.node.create_subscription(PointCloud2, "/maem/poses", on_poses, DATA_QOS),
        bg.node.create_subscription(PointCloud2, "/maem/clusters", on_clusters, DATA_QOS),
    ]
    bg.watch_diagnostics()
    return bg.start()


def _unready(listener, cameras: Sequence[str]) -> list[str]:
    """The links not yet matched at both ends: publishers -> association (the publishers wait
    for their end themselves) -> triangulation -> the listener."""
    from maem_ros.ros.probe import fusion_links, unmatched_links

    ours = [] if listener.subs[0].get_publisher_count() else ["/maem/poses -> listener"]
    return ours + unmatched_links(listener.diagnostics_snapshot(), fusion_links(cameras, image_topic=None))


def _ros_env(env: dict[str, str]) -> list[str]:
    """NAME=value of the variables the publishers need (``ip netns exec`` keeps the environment,
    spelled out so a sudo wrapper cannot drop them)."""
    keys = (
        "ROS_DOMAIN_ID",
        "ROS_AUTOMATIC_DISCOVERY_RANGE",
        "ROS_STATIC_PEERS",
        "FASTRTPS_DEFAULT_PROFILES_FILE",
        "PYTHONUNBUFFERED",
        "OMP_NUM_THREADS",
        "PATH",
    )
    return [f"{k}={env[k]}" for k in keys if k in env]


def run_live(a: argparse.Namespace) -> dict[str, Any]:
    """Run the live benchmark in a fresh work folder, removed afterwards (the messages, 3 GB
    for 300 full-mesh frames, stay in messages_dir() for the next run); a failure's error
    carries the logs."""
    work = Path(tempfile.mkdtemp(prefix="maem_live_"))
    try:
        return _run_live(a, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _run_live(a: argparse.Namespace, work: Path) -> dict[str, Any]:
    params, rig = _write_live_params(a, work)
    env, profile = _live_env(a)
    run = _run_graph(a, work, params, rig, env)
    return live_report(a, params, rig, profile, run)


def _write_live_params(a: argparse.Namespace, work: Path) -> tuple[Path, Any]:
    """WORK/params.yaml (--params with the frontend's scene size and the nodes' overload
    policy; the bag's rig when --bag has one) and the rig it names."""
    from maem_ros.params import load_node_params
    from maem_ros.ros.params import load_rig_param
    from maem_ros.tools.bench.latency import write_params

    policy = {
        **({"max_backlog": a.max_backlog} if a.max_backlog is not None else {}),
        **({"keep_every_set": True} if a.keep_every_set else {}),
        **({"catch_up": a.catch_up} if a.catch_up else {}),
    }
    assoc_over = {**({"max_wait": a.max_wait} if a.max_wait else {}), **policy} or None
    params = write_params(
        a.params,
        work / "params.yaml",
        # the scene simulated at the publishing rate, as a camera at that rate stamps its frames
        # (1/rate apart) and sees people move: the nodes measure the frame period from the stamps
        frontend={"frames": max(a.frames, 1), "num_vertices": a.vertices, "fps": a.rate},
        association=assoc_over,
        triangulation=policy or None,
    )
    if a.bag is not None:
        from maem_ros import bagio

        rig_yaml = bagio.read_rig_yaml(a.bag)
        if rig_yaml:
            (work / "rig.yaml").write_text(rig_yaml)
            params = write_params(
                params,
                work / "params.yaml",
                association={"rig": str(work / "rig.yaml")},
                triangulation={"rig": str(work / "rig.yaml")},
            )
    return params, load_rig_param(load_node_params(params, "association").get("rig", ""))


def _live_env(a: argparse.Namespace) -> tuple[dict[str, str], str | None]:
    """The child processes' environment, and the shipped DDS profile it names (None: the
    user's, or Fast DDS defaults with --no-profile)."""
    from maem_ros.ros.process import DDS_PROFILE_VARS, use_shipped_dds_profile

    profile = None if a.no_profile else use_shipped_dds_profile()
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    if a.no_profile:
        for v in DDS_PROFILE_VARS:
            env.pop(v, None)
    return env, profile


@dataclass
class _Graph:
    """The run's processes: the nodes and publishers, this process's listener, the CPU hog."""

    group: Any  # tools/processes.ProcessGroup
    listener: Any = None
    hog: subprocess.Popen | None = None


def _run_graph(a: argparse.Namespace, work: Path, params: Path, rig, env: dict[str, str]) -> Observed:
    """Start the nodes and one publisher per camera, wait until every link matched, run the
    timed publication, stop everything."""
    from maem_ros.tools.processes import ProcessGroup

    graph = _Graph(ProcessGroup(work / "logs", env))
    try:
        _start_graph(a, graph.group, work, params, rig, env)
        graph.listener = _listener()
        _wait_ready(a, graph, work, rig)
        run = _timed_run(a, graph, work, rig)
    finally:
        codes, forced = _stop_graph(graph)
    run.codes, run.forced = codes, forced
    return run


def _start_graph(a: argparse.Namespace, group, work: Path, params: Path, rig, env: dict[str, str]) -> None:
    from maem_ros.tools.processes import module_command, node_command

    for kind in ("association", "triangulation"):
        group.start(kind, node_command(kind, params))
    for cam in rig.names:
        cmd = module_command(
            "maem_ros.tools.bench.live",
            "--publish",
            cam,
            "--params",
            str(params),
            "--work",
            str(work),
            "--messages",
            str(messages_dir(a)),
            "--frames",
            str(a.frames),
            "--rate",
            f"{a.rate}",
            "--wire",
            a.wire,
            "--vertex-stride",
            str(a.vertex_stride),
            "--vertex-count",
            str(a.vertex_count),
        )
        cmd += (["--bag", str(a.bag)] if a.bag else []) + (["--no-profile"] if a.no_profile else [])
        if a.publisher_netns:  # the camera machines: another network namespace
            cmd = ["ip", "netns", "exec", a.publisher_netns, "env", *_ros_env(env), *cmd]
        group.start(f"publisher_{cam}", cmd)


def _wait_ready(a: argparse.Namespace, graph: _Graph, work: Path, rig) -> None:
    """Until every publisher built its messages and every link of the graph matched (raises
    RuntimeError with the logs after --startup-timeout s or when a process exits)."""
    group = graph.group
    deadline = time.monotonic() + a.startup_timeout
    while not all((work / f"{c}.ready").exists() for c in rig.names):
        if group.dead():
            raise RuntimeError(f"process exited during start-up: {group.dead()}\n{group.logs()}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"publishers not ready after {a.startup_timeout:.0f} s\n{group.logs()}")
        time.sleep(0.1)
    while unready := _unready(graph.listener, rig.names):
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"graph not matched after {a.startup_timeout:.0f} s: {unready}\n{group.logs()}"
            )
        time.sleep(0.05)


def _timed_run(a: argparse.Namespace, graph: _Graph, work: Path, rig) -> Observed:
    """Give the publishers a common start time (with --stress, start the CPU hog), wait for
    the last poses (at most --drain s after the last frame), collect what the listener saw."""
    from maem_ros.tools.bench.live_runs import hog_window, start_hog

    group, listener = graph.group, graph.listener
    messages = {c: pickle.loads((messages_dir(a) / f"{c}.pkl").read_bytes()) for c in rig.names}
    stamps = [s for s, _ in messages[rig.names[0]]]
    procs = list(group.procs.values())
    cpu0 = {p.name: p.cpu_seconds() for p in procs}
    machine0 = cpu_times()
    t0 = time.time() + 0.5
    hog_at = None
    if a.stress:
        hog_at = hog_window(t0, len(stamps), a.rate, a.stress)
        graph.hog = start_hog(hog_at[0], a.stress)
    (work / "start.tmp").write_text(repr(t0))
    (work / "start.tmp").rename(work / "start")  # atomic: a publisher never reads it half
    end = t0 + len(stamps) / a.rate
    while time.time() < end + a.drain and not (time.time() > end and stamps[-1] in listener.poses):
        failed = {n: c for n, c in group.dead().items() if c != 0}
        if failed:
            raise RuntimeError(f"process failed during the run: {failed}\n{group.logs()}")
        time.sleep(0.05)
    wall = time.time() - t0
    cpu1 = {p.name: p.cpu_seconds() for p in procs}
    machine1 = cpu_times()
    time.sleep(1.2)  # one more /diagnostics period (the publishers' lateness files too)
    late = {
        c: [float(x) for x in eval_list((work / f"{c}.late").read_text())]
        for c in rig.names
        if (work / f"{c}.late").exists()
    }
    with listener.lock:
        poses = dict(listener.poses)
        clusters = dict(listener.clusters)
        diags = dict(listener.diagnostics)
    return Observed(
        stamps=stamps,
        messages=messages,
        t0=t0,
        wall=wall,
        cpu0=cpu0,
        cpu1=cpu1,
        poses=poses,
        diags=diags,
        hog_at=hog_at,
        clusters=clusters,
        publisher_late_s=late,
        cpu_steal_pct=steal_pct(machine0, machine1),
    )


def eval_list(text: str) -> list[float]:
    """A publisher's lateness file (a Python list of floats, written by this module)."""
    import ast

    return [float(x) for x in ast.literal_eval(text)]


def _stop_graph(graph: _Graph) -> tuple[dict[str, int | None], Any]:
    """Let the publishers end by themselves, stop the nodes, close the listener, kill the hog;
    returns the exit codes and the processes whose shutdown watchdog forced their exit."""
    group = graph.group
    publishers = [n for n in group.procs if n.startswith("publisher_")]
    stop_by = time.monotonic() + 10.0  # they exit by themselves after the last frame
    while time.monotonic() < stop_by and len(group.dead(publishers)) < len(publishers):
        time.sleep(0.05)
    codes = group.stop(timeout_s=15.0)
    forced = group.forced_exits()
    if failed_names := [n for n, c in codes.items() if c != 0]:
        # the work folder and its logs go when the run ends: say here why they failed
        print(f"maem-bench --live: exit codes {codes}\n{group.logs(names=failed_names)}", file=sys.stderr)
    if graph.listener is not None:
        graph.listener.close()
    if graph.hog is not None and graph.hog.poll() is None:
        graph.hog.kill()
    return codes, forced


def add_live_arguments(p: argparse.ArgumentParser) -> None:
    """The --live options of maem-bench (--frames, --wire, --vertices, --params are shared)."""
    g = p.add_argument_group("live benchmark (--live)")
    g.add_argument(
        "--live",
        action="store_true",
        help="publish detections at camera rate through the node graph (see above)",
    )
    g.add_argument(
        "--bag", type=Path, default=None, help="--live: publish this bag's recorded /<cam>/detections"
    )
    g.add_argument(
        "--rate",
        type=float,
        default=30.0,
        help="--live: frames per second (the synthetic scene is simulated at this rate)",
    )
    g.add_argument(
        "--vertex-stride", type=int, default=1, help="--live: send every n-th vertex (announced subset)"
    )
    g.add_argument(
        "--vertex-count",
        type=int,
        default=0,
        help="--live: send this many of those vertices, spread evenly (announced subset; 0 = all)",
    )
    g.add_argument("--max-wait", type=float, default=None, help="--live: association max_wait, s")
    g.add_argument(
        "--max-backlog",
        type=float,
        default=None,
        help="--live: the nodes' max_backlog, s (skip frames that waited that long "
        "for the node; default: their automatic bound, 4 frame periods)",
    )
    g.add_argument(
        "--catch-up",
        choices=("newest", "stale"),
        default=None,
        help="--live: the nodes' catch_up (what a node that fell behind skips; default: theirs, newest)",
    )
    g.add_argument(
        "--keep-every-set",
        action="store_true",
        help="--live: the nodes process every frame however far behind (what a "
        "replay wanting every frame sets; the live default skips stale ones)",
    )
    from maem_ros.tools.bench.live_runs import add_arguments as add_runs_arguments

    add_runs_arguments(g)
    g.add_argument("--drain", type=float, default=3.0, help="--live: seconds to wait for the last poses")
    g.add_argument(
        "--startup-timeout",
        type=float,
        default=180.0,
        help="--live: seconds for publishers to build messages and match",
    )
    g.add_argument(
        "--no-profile", action="store_true", help="--live: Fast DDS defaults instead of config/fastdds.xml"
    )
    g.add_argument(
        "--publisher-netns",
        default=None,
        metavar="NS",
        help="--live: run the camera publishers in network namespace NS (ip netns; "
        "root), as separate machines (see scripts/netns_link.sh)",
    )


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
    p.add_argument("--messages", required=True, help="folder of the messages (CAM.pkl)")
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
