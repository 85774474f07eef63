"""maem-demo: replay the demo bag through the real node graph; print accuracy, timing and latency.

    maem-demo [--bag bags/demo] [--out out/demo] [--frames N | --duration S] [--rate R]
              [--params config/demo.yaml] [--keep-going] [--frontends | --no-graph]
    maem-demo --make-bag bags/demo        (regenerate the committed demo bag, seeded)
    maem-demo --bag BAG --backend mediapipe --out out/real   (real images, e.g. maem-make-bag --videos)

Graph mode (default) runs, each as its own process with one params file (OUT/params.yaml:
--params plus what the bag says, i.e. its rig): maem-record (/maem/poses, /maem/skeletons,
/diagnostics -> OUT/record), maem-association, maem-triangulation, and last maem-play, which
publishes the bag's recorded /<cam>/detections in real time (--rate 1.0, 30 fps): the live path
a user sees from the fusion machine, with a progress line. --frontends instead runs one
maem-frontend per camera (synthetic backend on /<cam>/image_raw/compressed: it regenerates the
full-resolution detections of each image stamp from the bag's scene description; association
max_wait 1 s as the six frontends share the CPU) and plays the bag's images without its
recorded detections, by default at rate 0.05. The association and triangulation run with
``keep_every_set: true``: the demo scores every frame, so nodes that fall behind on this machine
process every frame late instead of skipping the stale ones as a live graph does (said in the
output). At the end every process gets SIGINT and its exit
code is checked. --no-graph runs the core pipeline on the bag's recorded (vertex-subset)
detections in this process instead.

Printed: the maem-eval accuracy table against the bag's /maem/gt_poses (same metrics, see
maem-eval --help), per-stage timing from the last recorded /diagnostics of each node,
end-to-end latency and frames dropped. Written to OUT: report.json, snapshot_<cam>.png
(skeletons projected on a camera image), court.png (top-down view), logs/, record/.
report.json also has people_per_frame (people on /maem/poses per played frame),
reprojection_px_mean (see demo_metrics.REPROJECTION_DEFINITION) and bone_length_cv.

--backend mediapipe runs the frontends on the bag's images with multi-person BlazePose (the
optional mediapipe extra; default params config/mediapipe.yaml). Four CPU frontends can take
seconds per image each on a small machine, far slower than the 60 fps capture, so the replay
goes in lockstep:
maem-play publishes the next frame as soon as /maem/clusters has the last one (--lockstep,
at most 60 s per frame), at --rate (default 1) from there, and the images go reliable
(--reliable-images, frontends image_reliability: reliable): no image is lost to a full
best-effort queue and no frame set to the association's max_wait. A bag without ground truth
is reported without the accuracy table.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from maem_ros import bagio
from maem_ros.core.association import pipeline as association
from maem_ros.core.association.pipeline import associate
from maem_ros.core.errors import InputError
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.sync import capture_stamp_ns, match_capture_times
from maem_ros.core.triangulation import ransac_kernel as triangulation_kernel
from maem_ros.core.triangulation.ransac import triangulate
from maem_ros.params import load_node_params, resolve_config_path
from maem_ros.ros.probe import ArrivalListener, fusion_links, unmatched_links
from maem_ros.ros.wire import msg_to_detections
from maem_ros.tools.demo.demo_bag import (
    BAG_VERTICES,
    DEMO_SCENE,
    JPEG_QUALITY,
    DemoBag,
    check_scene,
    ensure_bag,
    image_topic,
    load_bag,
    log,
    make_demo_bag,
    trim_bag,
)
from maem_ros.tools.demo.demo_report import (
    LATENCY_DEFINITION,
    GraphRun,
    format_timing,
    latencies_ms,
    print_accuracy,
    print_run_summary,
    recorded_diagnostics,
    recorded_poses,
    score,
    stage_timing,
    write_pictures,
)
from maem_ros.tools.eval.evaluate import load_params, to_sportcenter13
from maem_ros.tools.eval.results import jsonable
from maem_ros.tools.processes import Proc, ProcessGroup, module_command, node_command

#: default playback rate of the recorded detections: real time
DEFAULT_RATE = 1.0
#: default playback rate with --frontends (1.5 fps): each synthetic frontend regenerates
#: 18,439-vertex detections of ~12 people per image, a CPU-heavy step; all six get a frame at
#: the same moment and share the machine's cores with the rest of the graph, so on a small
#: machine faster replays drop frames
FRONTENDS_RATE = 0.05
#: --backend -> (default params file, default playback rate with frontends (None: FRONTENDS_RATE),
#: association max_wait s). mediapipe: four CPU frontends, each taking up to seconds per
#: image on a small machine, share its cores, so the replay goes in lockstep and the
#: association waits up to 3 s for a frame's last camera
BACKENDS = {"synthetic": ("demo.yaml", None, 1.0), "mediapipe": ("mediapipe.yaml", 1.0, 3.0)}
#: backends whose replay goes in lockstep with the graph (the player publishes the next frame
#: when /maem/clusters has the last one, images reliable): CPU frontends slower than the
#: recording would otherwise lose images (best-effort queues) or miss their frame set
LOCKSTEP_BACKENDS = ("mediapipe",)
LOCKSTEP_TOPIC = "/maem/clusters"
#: longest lockstep wait per frame (s): four frontends at up to a few s per image each
LOCKSTEP_TIMEOUT_S = 60.0
RECORD_TOPICS = ("/maem/poses", "/maem/skeletons", "/maem/clusters", "/diagnostics")


# ---------------------------------------------------------------------------------------------
# params
# ---------------------------------------------------------------------------------------------
#: frontend scene keys that would override scene_dict: set to their "unset" sentinels
_SCENE_SENTINELS = {"seed": -1, "difficulty": "", "frames": 0, "num_vertices": 0, "fps": 0.0,
                    "start_stamp_ns": -1}


def node_section(data: dict, node: str) -> dict:
    """The ros__parameters of ``node`` in a params dict, merged from its "node", "/node" and
    "/**/node" sections into one "/**/node" section (which also matches the namespaced
    frontends, /camera_0/frontend; a plain "frontend" key matches only /frontend)."""
    merged: dict = {}
    for key in (node, f"/{node}", f"/**/{node}"):
        merged.update(((data.pop(key, None) or {}).get("ros__parameters")) or {})
    data[f"/**/{node}"] = {"ros__parameters": merged}
    return merged


def write_params(base: str, out: Path, rig_path: Path, scene_config: dict | None,
                 max_wait_s: float | None = 1.0, frontends: bool = True,
                 backend: str | None = None) -> Path:
    """``base`` params file with the bag's rig for every node; with ``frontends``, for them
    compressed images and the bag's scene description (the synthetic backend regenerates from
    it); for the association ``max_wait_s`` (s, None = the params file's; the six frontends
    share the CPU, so one frame's detections arrive spread over a few hundred ms); ``backend``
    replaces the frontends' backend."""
    data = yaml.safe_load(resolve_config_path(base).read_text()) or {}
    nodes = {name: node_section(data, name)
             for name in ("frontend", "association", "triangulation")}
    data.setdefault("/**", {}).setdefault("ros__parameters", {})["rig"] = str(rig_path)
    for section in nodes.values():
        if "rig" in section:
            section["rig"] = str(rig_path)
    fe = nodes["frontend"]
    fe["image_transport"] = "compressed"
    if backend is not None:
        fe["backend"] = backend
    if backend in LOCKSTEP_BACKENDS:  # the player publishes them reliable: lose none
        fe["image_reliability"] = "reliable"
    if frontends and fe.get("backend", "synthetic") == "synthetic":
        if scene_config is None:
            raise ValueError("the bag has no scene description (/maem/scene): the synthetic "
                             "frontend cannot regenerate its detections")
        fe.update(_SCENE_SENTINELS)
        fe["scene_dict"] = json.dumps(scene_config, sort_keys=True)
        fe["scene_rig"] = str(scene_config.get("rig", ""))
    if max_wait_s is not None:
        nodes["association"]["max_wait"] = float(max_wait_s)
    for name in ("association", "triangulation"):  # the demo scores every frame of the bag
        nodes[name]["keep_every_set"] = True
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


# ---------------------------------------------------------------------------------------------
# the graph: processes, wiring, replay
# ---------------------------------------------------------------------------------------------
def child_env() -> dict[str, str]:
    """Environment of the children: a private random ROS_DOMAIN_ID unless the user set one, and
    localhost-only discovery, so two demos (or a demo and a test run) never hear each other."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def missing_links(listener: ArrivalListener, cameras: Sequence[str],
                  frontends: bool = True) -> list[str]:
    """What is not wired yet (empty = frontends, association, triangulation, recorder ready).

    The ROS graph must list every subscriber, and the links between the nodes must be matched
    at both ends (the nodes' /diagnostics): a message sent before its link matched is lost,
    though the graph already lists both nodes (CI saw the first 5 frames' clusters lost).
    /maem/poses: the recorder's and this listener's readers."""
    need = [(image_topic(c), 2, "frontend") for c in cameras] if frontends else []
    # without frontends the player publishes the detections: association + this listener
    need += [(f"/{c}/detections", 1 if frontends else 2, "association") for c in cameras]
    need += [("/maem/clusters", 1, "triangulation"), ("/maem/poses", 2, "recorder"),
             ("/maem/skeletons", 1, "recorder"), ("/diagnostics", 1, "recorder")]
    listed = [f"{topic} has no {who} subscriber" for topic, k, who in need
              if listener.count_subscribers(topic) < k]
    links = fusion_links(cameras, "image_raw/compressed" if frontends else None, sources=False)
    return listed + [f"{link} not matched" for link in unmatched_links(
        listener.diagnostics_snapshot(), links, at_least={"matched_subscribers/maem/poses": 2})]


class DemoError(RuntimeError):
    """The graph could not run (start-up failure, crash without --keep-going)."""


def _crash_text(proc: Proc, code: int | None) -> str:
    if code is None:
        what = "did not exit within the SIGINT timeout; killed"
    elif code < 0:
        what = f"killed by signal {signal.Signals(-code).name}"
    else:
        what = f"exit code {code}"
    return f"{proc.name}: {what}\n    " + "\n    ".join(proc.tail().rstrip().splitlines()[-12:])


def run_graph(bag: Path, demo: DemoBag, stamps: Sequence[int], params: Path, out: Path,
              rate: float, keep_going: bool, startup_timeout_s: float = 60.0,
              drain_s: float = 5.0, frontends: bool = False, lockstep: bool = False) -> GraphRun:
    """Start recorder + nodes, wait until wired, play ``bag`` (whose frames are ``stamps``:
    its recorded detections, or with ``frontends`` its images; ``lockstep``: one frame at a
    time, each when the last one's clusters came, images reliable), wait until every frame has
    poses (or none came for ``drain_s``), SIGINT everything."""
    warm_numba_cache()
    group = ProcessGroup(out / "logs", child_env())
    record = out / "record"
    nodes = ([f"frontend_{c}" for c in demo.cameras] if frontends else []) + \
        ["association", "triangulation"]
    listener = None
    crashed: dict[str, str] = {}
    try:
        group.start("recorder", module_command("maem_ros.ros.recorder_node", str(record),
                                               "--topics", *RECORD_TOPICS))
        for c in (demo.cameras if frontends else []):
            group.start(f"frontend_{c}", node_command("frontend", params, f"/{c}"))
        for kind in ("association", "triangulation"):
            group.start(kind, node_command(kind, params))
        # the listener (this process) joins the children's domain and discovery range
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE",
                              group.env["ROS_AUTOMATIC_DISCOVERY_RANGE"])
        if frontends:
            listener = ArrivalListener([image_topic(c) for c in demo.cameras],
                                       int(group.env["ROS_DOMAIN_ID"]))
        else:
            from sensor_msgs.msg import PointCloud2
            listener = ArrivalListener([f"/{c}/detections" for c in demo.cameras],
                                       int(group.env["ROS_DOMAIN_ID"]), input_type=PointCloud2)
        _wait_wired(group, listener, demo.cameras, startup_timeout_s, frontends)
        t0 = time.monotonic()
        played, dropped = (("/*/image_raw/compressed", "/*/detections") if frontends
                           else ("/*/detections", "/*/image_raw/compressed"))
        group.start("player", module_command(
            "maem_ros.ros.player_node", str(bag), "--rate", f"{rate:g}", "--delay", "1.0",
            "--wait-subscribers", f"{startup_timeout_s:g}", "--wait-topics", played,
            "--min-subscribers", "2",  # the frontend / association and this process's listener
            "--exclude", dropped, bagio.GT_TOPIC,
            *(("--lockstep", LOCKSTEP_TOPIC, "--lockstep-timeout", f"{LOCKSTEP_TIMEOUT_S:g}",
               "--reliable-images") if lockstep else ())))
        crashed.update(_watch_play(group, nodes + ["recorder"], keep_going,
                                   _progress(listener, len(stamps))))
        _drain(group, listener, stamps, drain_s, nodes, crashed, keep_going)
        wall = time.monotonic() - t0
        time.sleep(1.3)  # one more /diagnostics period reaches the recorder
        codes = group.stop(nodes)
        codes["player"] = group.procs["player"].popen.returncode
        codes.update(group.stop(["recorder"], timeout_s=15.0))
    finally:
        group.shutdown()
        if listener is not None:
            image_t, poses_t = listener.snapshot()
            listener.close()
    for name, code in codes.items():
        if code != 0 and name not in crashed:
            crashed[name] = _crash_text(group.procs[name], code)
    return GraphRun(codes, crashed, image_t, poses_t, wall, record)


def warm_numba_cache() -> None:
    """Compile the gates' and RANSAC kernels here (numba's on-disk cache) so the nodes load
    them at start instead of compiling them for seconds while frames queue up."""
    t0 = time.monotonic()
    association.warmup()
    triangulation_kernel.warmup()
    dt = time.monotonic() - t0
    if dt > 1.0:
        log(f"compiled the numba kernels in {dt:.1f} s (cached for the nodes)")


def _progress(listener: ArrivalListener, total: int, period_s: float = 1.0):
    """A callable printing one progress line (frames in, frames with poses) every period_s;
    rewritten in place on a terminal."""
    state = {"next": time.monotonic() + period_s}
    tty = sys.stdout.isatty()

    def show(final: bool = False) -> None:
        now = time.monotonic()
        if not final and now < state["next"]:
            return
        state["next"] = now + period_s
        inputs, poses = listener.snapshot()
        text = f"maem-demo: played {len(inputs)}/{total} frames, poses for {len(poses)}"
        print(("\r" + text + ("\n" if final else "")) if tty else text, end="" if tty else "\n",
              flush=True)
    return show


def _wait_wired(group: ProcessGroup, listener: ArrivalListener, cameras: Sequence[str],
                timeout_s: float, frontends: bool = True) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        dead = group.dead()
        if dead:
            raise DemoError("process exited during start-up:\n  " + "\n  ".join(
                _crash_text(group.procs[n], c) for n, c in dead.items()))
        missing = missing_links(listener, cameras, frontends)
        if not missing:
            return
        if time.monotonic() > deadline:
            raise DemoError(f"graph not wired after {timeout_s:.0f} s: {'; '.join(missing)}")
        time.sleep(0.2)


def _watch_play(group: ProcessGroup, watched: list[str], keep_going: bool,
                progress=None) -> dict[str, str]:
    """Wait for the player to finish; a crashed node aborts unless ``keep_going``."""
    crashed: dict[str, str] = {}
    player = group.procs["player"].popen
    while player.poll() is None:
        _check_crashes(group, watched, crashed, keep_going)
        if progress is not None:
            progress()
        time.sleep(0.1)
    _check_crashes(group, watched, crashed, keep_going)
    if progress is not None:
        progress(final=True)
    return crashed


def _check_crashes(group: ProcessGroup, watched: list[str], crashed: dict[str, str],
                   keep_going: bool) -> None:
    for name, code in group.dead(watched).items():
        if name not in crashed:
            crashed[name] = _crash_text(group.procs[name], code)
            if keep_going:
                log(f"NODE CRASHED (--keep-going: replay continues): {crashed[name]}")
            else:
                raise DemoError(f"{name} crashed during the replay (use --keep-going to finish "
                                f"the replay anyway):\n  {crashed[name]}")


def _drain(group: ProcessGroup, listener: ArrivalListener, stamps: Sequence[int], idle_s: float,
           nodes: list[str], crashed: dict[str, str], keep_going: bool) -> None:
    """Wait until every frame has its poses, or no new poses arrived for ``idle_s``."""
    last_n, last_change = -1, time.monotonic()
    while time.monotonic() - last_change < idle_s:
        _check_crashes(group, nodes + ["recorder"], crashed, keep_going)
        _, poses = listener.snapshot()
        if all(s in poses for s in stamps):
            return
        if len(poses) != last_n:
            last_n, last_change = len(poses), time.monotonic()
        time.sleep(0.1)


# ---------------------------------------------------------------------------------------------
# offline (--no-graph)
# ---------------------------------------------------------------------------------------------
@dataclass
class OfflinePose:
    ids: np.ndarray
    joints: np.ndarray
    scores: np.ndarray


def run_offline(demo: DemoBag, rig, params: str, stamps: Sequence[int]
                ) -> tuple[dict[int, OfflinePose], list[float]]:
    """Association + triangulation of the bag's recorded detections, per frame, in process."""
    assoc, tri = load_params(params)
    frames: dict[int, dict[str, Any]] = {s: {} for s in stamps}
    topics = [f"/{c}/detections" for c in demo.cameras]
    if not any(t in demo.info.topics for t in topics):
        raise ValueError(f"bag {str(demo.path)!r}: no /<camera>/detections to run --no-graph on")
    offsets = {c: rig[c].time_offset for c in rig.names}
    late = max([0.0] + [-o for o in offsets.values()])  # s, capture time beyond the stamps
    stop = stamps[-1] + 1 + int(round(late * 1e9)) if stamps else None
    received: dict[str, list] = {}
    for m in bagio.read_messages(demo.path, topics, stop_ns=stop, info=demo.info):
        dets = msg_to_detections(m.decode(), m.topic, rig.names)
        received.setdefault(dets.camera, []).append(dets)
    # each camera's message captured nearest each frame (stamp + the rig's time_offset)
    tolerance = int(np.median(np.diff(stamps)) // 2) if len(stamps) > 1 else 0
    for cam, msgs in received.items():
        msgs.sort(key=lambda d: d.stamp_ns)
        index = match_capture_times(stamps, [d.stamp_ns for d in msgs], offsets[cam], tolerance)
        for s, k in zip(stamps, index):
            if k >= 0:
                dets = msgs[k]
                dets.stamp_ns = capture_stamp_ns(dets.stamp_ns, offsets[cam])
                frames[s][cam] = dets
    out, ms = {}, []
    for s in stamps:
        t0 = time.perf_counter()
        result = associate(rig, frames[s], assoc)
        poses = triangulate(rig, frames[s], result.clusters, tri)
        ms.append(1e3 * (time.perf_counter() - t0))
        joints = np.asarray(poses.joints, np.float64)
        joints = to_sportcenter13(joints) if len(joints) else np.zeros((0, 13, 3))
        out[s] = OfflinePose(np.arange(len(joints)), joints, np.asarray(poses.scores, np.float64))
    return out, ms


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="maem-demo",
                                description=__doc__.split("\n\n")[0].split(": ", 1)[1],
                                epilog=f"{__doc__.split(chr(10) * 2, 2)[2]}\n{LATENCY_DEFINITION}.",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bag", type=Path, default=None,
                   help="input bag, which must exist (default bags/demo, generated first when "
                   "missing; --make-bag DIR builds one elsewhere)")
    p.add_argument("--out", type=Path, default=Path("out/demo"),
                   help="output folder (default out/demo)")
    p.add_argument("--params", default=None,
                   help="params file (default config/demo.yaml; config/mediapipe.yaml with "
                   "--backend mediapipe)")
    p.add_argument("--backend", choices=sorted(BACKENDS), default="synthetic",
                   help="frontend backend of the graph (default synthetic: the simulated "
                   "detections of the bag's scene; mediapipe: BlazePose on the bag's images)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frames", type=int, default=None, help="play only the first N frames")
    g.add_argument("--duration", type=float, default=None, metavar="S",
                   help="play only the first S seconds of bag time")
    p.add_argument("--rate", type=float, default=None,
                   help=f"playback rate (default {DEFAULT_RATE}, with --frontends "
                        f"{FRONTENDS_RATE}; the bag is 30 fps; 1 with --backend mediapipe, in lockstep "
                        "with the graph)")
    p.add_argument("--keep-going", action="store_true",
                   help="finish the replay when a node crashes (reported at the end, exit 1)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--no-graph", action="store_true",
                      help="offline: core association + triangulation on the bag's recorded "
                      "detections")
    mode.add_argument("--frontends", action="store_true",
                      help="run the synthetic frontends on the bag's images instead of playing "
                      "its recorded detections")
    p.add_argument("--startup-timeout", type=float, default=60.0, metavar="S",
                   help="give up when the graph is not wired after S seconds (default 60)")
    p.add_argument("--make-bag", type=Path, default=None, metavar="DIR",
                   help=f"only build the demo bag into DIR (seeded; JPEG quality {JPEG_QUALITY}, "
                   f"{BAG_VERTICES} mesh vertices per recorded detection) and exit")
    p.add_argument("--bag-frames", type=int, default=DEMO_SCENE["frames"], metavar="N",
                   help=f"frames of a generated demo bag (default {DEMO_SCENE['frames']})")
    return p


def played_frames(demo: DemoBag, frames: int | None, duration: float | None) -> int:
    n = len(demo.stamps)
    if frames is not None:
        n = min(n, frames)
    if duration is not None:
        n = min(n, max(1, int(np.floor(duration * demo.fps + 1e-9)) + 1))
    return n


def prepare_out(out: Path) -> None:
    """Create ``out``; remove what a previous demo run wrote there (only those entries)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("record", "logs", "input", "params.yaml", "rig.yaml", "report.json", "court.png"):
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in out.glob("snapshot_*.png"):
        p.unlink()


def main(argv: Sequence[str] | None = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    if a.backend != "synthetic":
        if a.no_graph:
            p.error(f"--backend {a.backend} runs frontends on the bag's images; --no-graph has none")
        a.frontends = True  # only the frontends see images
    a.params = a.params or BACKENDS[a.backend][0]
    if a.rate is None and a.frontends:
        a.rate = BACKENDS[a.backend][1]
    if a.make_bag is not None:
        try:
            make_demo_bag(a.make_bag, frames=a.bag_frames)
        except (ValueError, RuntimeError) as e:
            print(f"maem-demo: {e}", file=sys.stderr)
            return 2
        return 0
    if a.rate is None:
        a.rate = FRONTENDS_RATE if a.frontends else DEFAULT_RATE
    if not a.rate > 0:
        print(f"maem-demo: --rate must be > 0, got {a.rate}", file=sys.stderr)
        return 2
    if (a.frames is not None and a.frames < 1) or (a.duration is not None and a.duration <= 0):
        print("maem-demo: --frames / --duration must be positive", file=sys.stderr)
        return 2
    t_start = time.monotonic()
    try:
        return run_demo(a, t_start)
    except InputError as e:  # the bag (missing, damaged, not a demo bag), the params file
        print(f"maem-demo: {e}", file=sys.stderr)
        return 2
    except (ValueError, DemoError) as e:
        print(f"maem-demo: {e}", file=sys.stderr)
        return 1


def offline_mode(a: argparse.Namespace, demo: DemoBag, rig, stamps: list[int]
                 ) -> tuple[int, dict[int, Any], dict[str, Any]]:
    """--no-graph: (exit code, poses by stamp, report entries)."""
    poses, ms = run_offline(demo, rig, a.params, stamps)
    metrics = score(demo, stamps, {s: (p.joints, p.scores) for s, p in poses.items()})
    metrics["association_ms_median"] = float(np.median(ms))
    print_accuracy("offline (bag detections)", metrics)
    print(f"\ncore association + triangulation per frame: median {np.median(ms):.1f} ms, "
          f"p99 {np.percentile(ms, 99):.1f} ms (this process, bag's vertex subset)")
    return 0, poses, {"metrics": metrics, "pipeline_ms_median": float(np.median(ms))}


def graph_mode(a: argparse.Namespace, demo: DemoBag, rig_path: Path, stamps: list[int]
               ) -> tuple[int, dict[int, Any], dict[str, Any]]:
    """The node graph replay: (exit code, recorded poses by stamp, report entries)."""
    if a.frontends and a.backend == "synthetic":
        check_scene(demo)
    elif not a.frontends and not any(f"/{c}/detections" in demo.info.topics for c in demo.cameras):
        raise ValueError(f"bag {str(demo.path)!r}: no recorded /<camera>/detections to play "
                         f"(use --frontends to run the synthetic frontends on its images)")
    n = len(stamps)
    play_bag = demo.path if n == len(demo.stamps) else trim_bag(demo, a.out / "input", n)
    params = write_params(a.params, a.out / "params.yaml", rig_path.resolve(), demo.scene_config,
                          max_wait_s=BACKENDS[a.backend][2] if a.frontends else None,
                          frontends=a.frontends, backend=a.backend if a.frontends else None)
    lockstep = a.frontends and a.backend in LOCKSTEP_BACKENDS
    log("every frame is processed however late (association and triangulation "
        "keep_every_set: true; a live graph skips the frames it falls behind on)"
        + ("; the replay goes in lockstep with /maem/clusters" if lockstep else ""))
    run = run_graph(play_bag, demo, stamps, params, a.out, a.rate, a.keep_going,
                    startup_timeout_s=a.startup_timeout, frontends=a.frontends,
                    lockstep=lockstep)
    poses = recorded_poses(run.record)
    diags = recorded_diagnostics(run.record)
    metrics = score(demo, stamps, {s: (p.joints, p.scores) for s, p in poses.items()}) \
        if demo.gt else {}
    assoc = next((kv for name, kv in diags.items() if name.strip("/") == "association"), {})
    metrics["association_ms_median"] = float(assoc.get("time_ms/associate/median", "nan"))
    if demo.gt:
        print_accuracy("graph (maem-play -> frontends -> nodes)" if a.frontends
                       else "graph (maem-play detections -> nodes)", metrics)
    else:
        print("\nthe bag has no ground truth (/maem/gt_poses): no accuracy table")
    quality = real_capture_measures(run.record, Rig.load(rig_path), params, stamps, poses)
    rows = stage_timing(diags)
    print("\nper-stage timing (last /diagnostics of each node, over its last <= 200 frames):")
    print(format_timing(rows) if rows else "  no /diagnostics recorded")
    lat = latencies_ms(run.image_t, run.poses_t)
    dropped = [s for s in stamps if s not in poses]
    print_run_summary(a.rate, n, lat, dropped, diags, run)
    definition = LATENCY_DEFINITION if a.frontends else LATENCY_DEFINITION.replace(
        "/<cam>/image_raw/compressed", "/<cam>/detections").replace(
        "the frontends, synchronisation", "synchronisation")
    report = {"metrics": metrics, "latency_definition": definition,
              "timing": [dict(zip(("node", "stage", "median_ms", "p99_ms", "processed",
                                   "dropped"), r)) for r in rows],
              "latency_ms_median": float(np.median(lat)) if len(lat) else None,
              "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
              "frames_dropped": len(dropped), "exit_codes": run.exit_codes, **quality,
              "crashed": run.crashed, "record": str(run.record), "replay_wall_s": run.wall_s}
    if run.crashed:
        print("\nNODE FAILURES:")
        for text in run.crashed.values():
            print(f"  {text}")
    return (1 if run.crashed else 0), poses, report


def open_demo_bag(a: argparse.Namespace) -> DemoBag:
    """The demo's input bag, read and checked; InputError (exit 2) when it is unusable."""
    bag = ensure_bag(a.bag, a.bag_frames)
    try:
        return load_bag(bag)
    except InputError:
        raise
    except ValueError as e:  # readable, but not a demo bag (no images, no rig ...)
        raise InputError(str(e), "bad_bag") from None


def real_capture_measures(record: Path, rig: Rig, params: Path, stamps: Sequence[int],
                          poses: dict[int, Any]) -> dict[str, Any]:
    """people_per_frame, reprojection and bone-length stability of the recorded run (printed)."""
    from maem_ros.core.skeleton import get_convention
    from maem_ros.params import load_node_params
    from maem_ros.tools.demo import demo_metrics as dm
    _, tri = load_params(str(params))
    conv = get_convention(load_node_params(params, "triangulation")
                          .get("output_convention", "sportcenter_13"))
    people = dm.people_per_frame(stamps, poses)
    reproj = dm.reprojection_summary(dm.reprojection_errors(record, rig, tri, stamps), tri.tau_kps)
    bones = dm.bone_length_cv(poses, conv)
    found = dm.joints_found(poses, conv)
    counts = np.bincount(people) if people else np.zeros(1, int)
    print("\npeople per frame (/maem/poses): " + ", ".join(
        f"{k}: {c} frames" for k, c in enumerate(counts) if c))
    if reproj["reprojection_pairs"]:
        print(f"reprojection error of the triangulated joints in their clusters' views: mean "
              f"{reproj['reprojection_px_mean']:.1f} px, median "
              f"{reproj['reprojection_px_median']:.1f} px, under tau_kps "
              f"{reproj['reprojection_px_mean_inliers']:.1f} px "
              f"({100 * reproj['reprojection_inlier_fraction']:.0f} % of "  # type: ignore[operator]
              f"{reproj['reprojection_pairs']} joint-views); all members "
              f"{reproj['reprojection_px_mean_all_members']:.1f} px "
              f"({reproj['reprojection_members_rejected']} of {reproj['reprojection_members']} "
              f"members left out by tau_member)")
    if found["joints_found"]:
        print("joints found per published person: " + ", ".join(
            f"{j} {100 * v:.0f} %" for j, v in found["joints_found"].items()))
    if bones["bone_length_cv"]:
        print(f"bone length coefficient of variation over {bones['bone_length_tracks']} tracks: "
              + ", ".join(f"{b} {100 * v:.1f} %" for b, v in bones["bone_length_cv"].items()))
    return {"people_per_frame": people, **reproj, **bones, **found,
            "reprojection_definition": dm.REPROJECTION_DEFINITION}


def run_demo(a: argparse.Namespace, t_start: float) -> int:
    load_node_params(a.params, "association")  # a bad params file: one line before any work
    demo = open_demo_bag(a)
    bag = demo.path
    prepare_out(a.out)
    stamps = demo.stamps[:played_frames(demo, a.frames, a.duration)]
    rig_path = a.out / "rig.yaml"
    rig_path.write_text(demo.rig_yaml)
    rig = Rig.load(rig_path)
    log(f"bag {str(bag)!r}: {len(demo.stamps)} frames x {len(demo.cameras)} cameras at "
        f"{demo.fps:.0f} fps; playing {len(stamps)} frames "
        + ("offline (--no-graph)" if a.no_graph else f"at rate {a.rate:g}"))
    mode = offline_mode(a, demo, rig, stamps) if a.no_graph else graph_mode(a, demo, rig_path,
                                                                            stamps)
    code, poses, entries = mode
    pictures = write_pictures(a.out, demo, rig, stamps, poses)
    report = {"bag": str(bag), "backend": a.backend, "frames_played": len(stamps),
              "cameras": demo.cameras,
              "mode": "offline" if a.no_graph else "graph", "rate": a.rate, **entries,
              "pictures": [str(p) for p in pictures], "wall_s": time.monotonic() - t_start}
    (a.out / "report.json").write_text(json.dumps(jsonable(report), indent=2))
    print(f"\nwrote {', '.join(str(p) for p in pictures) or 'no pictures (no frame with poses)'}, "
          f"{a.out / 'report.json'}")
    log(f"done in {report['wall_s']:.1f} s")
    return code


if __name__ == "__main__":
    sys.exit(main())
