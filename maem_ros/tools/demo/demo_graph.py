"""maem-demo's graph mode (tools/demo/demo.py): the params file the nodes get, the child
processes (maem-record, the frontends or none, maem-association, maem-triangulation, last
maem-play), the wait until every link is matched, the replay with a progress line, crash
watching and the drain until every frame has its poses."""

from __future__ import annotations

import json
import os
import random
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import yaml

from maem_ros import bagio
from maem_ros.core.association import pipeline as association
from maem_ros.core.triangulation import ransac_kernel as triangulation_kernel
from maem_ros.params import resolve_config_path
from maem_ros.ros.probe import ArrivalListener, fusion_links, unmatched_links
from maem_ros.tools.demo.demo_bag import DemoBag, image_topic, log
from maem_ros.tools.demo.demo_report import GraphRun
from maem_ros.tools.processes import Proc, ProcessGroup, module_command, node_command

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
_SCENE_SENTINELS = {
    "seed": -1,
    "difficulty": "",
    "frames": 0,
    "num_vertices": 0,
    "fps": 0.0,
    "start_stamp_ns": -1,
}


def node_section(data: dict, node: str) -> dict:
    """The ros__parameters of ``node`` in a params dict, merged from its "node", "/node" and
    "/**/node" sections into one "/**/node" section (which also matches the namespaced
    frontends, /camera_0/frontend; a plain "frontend" key matches only /frontend)."""
    merged: dict = {}
    for key in (node, f"/{node}", f"/**/{node}"):
        merged.update(((data.pop(key, None) or {}).get("ros__parameters")) or {})
    data[f"/**/{node}"] = {"ros__parameters": merged}
    return merged


def write_params(
    base: str,
    out: Path,
    rig_path: Path,
    scene_config: dict | None,
    max_wait_s: float | None = 1.0,
    frontends: bool = True,
    backend: str | None = None,
) -> Path:
    """``base`` params file with the bag's rig for every node; with ``frontends``, for them
    compressed images and the bag's scene description (the synthetic backend regenerates from
    it); for the association ``max_wait_s`` (s, None = the params file's; the six frontends
    share the CPU, so one frame's detections arrive spread over a few hundred ms); ``backend``
    replaces the frontends' backend."""
    data = yaml.safe_load(resolve_config_path(base).read_text()) or {}
    nodes = {name: node_section(data, name) for name in ("frontend", "association", "triangulation")}
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
            raise ValueError(
                "the bag has no scene description (/maem/scene): the synthetic "
                "frontend cannot regenerate its detections"
            )
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


def missing_links(listener: ArrivalListener, cameras: Sequence[str], frontends: bool = True) -> list[str]:
    """What is not wired yet (empty = frontends, association, triangulation, recorder ready).

    The ROS graph must list every subscriber, and the links between the nodes must be matched
    at both ends (the nodes' /diagnostics): a message sent before its link matched is lost,
    though the graph already lists both nodes (CI saw the first 5 frames' clusters lost).
    /maem/poses: the recorder's and this listener's readers."""
    need = [(image_topic(c), 2, "frontend") for c in cameras] if frontends else []
    # without frontends the player publishes the detections: association + this listener
    need += [(f"/{c}/detections", 1 if frontends else 2, "association") for c in cameras]
    need += [
        ("/maem/clusters", 1, "triangulation"),
        ("/maem/poses", 2, "recorder"),
        ("/maem/skeletons", 1, "recorder"),
        ("/diagnostics", 1, "recorder"),
    ]
    listed = [
        f"{topic} has no {who} subscriber" for topic, k, who in need if listener.count_subscribers(topic) < k
    ]
    links = fusion_links(cameras, "image_raw/compressed" if frontends else None, sources=False)
    return listed + [
        f"{link} not matched"
        for link in unmatched_links(
            listener.diagnostics_snapshot(), links, at_least={"matched_subscribers/maem/poses": 2}
        )
    ]


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


def _arrival_listener(cameras: Sequence[str], domain_id: int, frontends: bool) -> ArrivalListener:
    """This process's listener of the played inputs (images with ``frontends``, else the
    recorded detections) and of /maem/poses, on the graph's domain."""
    if frontends:
        return ArrivalListener([image_topic(c) for c in cameras], domain_id)
    from sensor_msgs.msg import PointCloud2

    return ArrivalListener([f"/{c}/detections" for c in cameras], domain_id, input_type=PointCloud2)


def _player_command(
    bag: Path, rate: float, startup_timeout_s: float, frontends: bool, lockstep: bool
) -> list[str]:
    """maem-play's command line for the graph replay: the images (``frontends``) or the
    recorded detections, never the ground truth; ``lockstep``: one frame per /maem/clusters."""
    played, dropped = (
        ("/*/image_raw/compressed", "/*/detections")
        if frontends
        else ("/*/detections", "/*/image_raw/compressed")
    )
    step = [
        "--lockstep",
        LOCKSTEP_TOPIC,
        "--lockstep-timeout",
        f"{LOCKSTEP_TIMEOUT_S:g}",
        "--reliable-images",
    ]
    return module_command(
        "maem_ros.ros.player_node",
        str(bag),
        "--rate",
        f"{rate:g}",
        "--delay",
        "1.0",
        "--wait-subscribers",
        f"{startup_timeout_s:g}",
        "--wait-topics",
        played,
        "--min-subscribers",
        "2",  # the frontend / association and this process's listener
        "--exclude",
        dropped,
        bagio.GT_TOPIC,
        *(step if lockstep else ()),
    )


def run_graph(
    bag: Path,
    demo: DemoBag,
    stamps: Sequence[int],
    params: Path,
    out: Path,
    rate: float,
    keep_going: bool,
    startup_timeout_s: float = 60.0,
    drain_s: float = 5.0,
    frontends: bool = False,
    lockstep: bool = False,
) -> GraphRun:
    """Start recorder + nodes, wait until wired, play ``bag`` (whose frames are ``stamps``:
    its recorded detections, or with ``frontends`` its images; ``lockstep``: one frame at a
    time, each when the last one's clusters came, images reliable), wait until every frame has
    poses (or none came for ``drain_s``), SIGINT everything."""
    warm_numba_cache()
    group = ProcessGroup(out / "logs", child_env())
    record = out / "record"
    nodes = ([f"frontend_{c}" for c in demo.cameras] if frontends else []) + ["association", "triangulation"]
    listener = None
    crashed: dict[str, str] = {}
    try:
        group.start(
            "recorder", module_command("maem_ros.ros.recorder_node", str(record), "--topics", *RECORD_TOPICS)
        )
        for c in demo.cameras if frontends else []:
            group.start(f"frontend_{c}", node_command("frontend", params, f"/{c}"))
        for kind in ("association", "triangulation"):
            group.start(kind, node_command(kind, params))
        # the listener (this process) joins the children's domain and discovery range
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", group.env["ROS_AUTOMATIC_DISCOVERY_RANGE"])
        listener = _arrival_listener(demo.cameras, int(group.env["ROS_DOMAIN_ID"]), frontends)
        _wait_wired(group, listener, demo.cameras, startup_timeout_s, frontends)
        t0 = time.monotonic()
        group.start("player", _player_command(bag, rate, startup_timeout_s, frontends, lockstep))
        crashed.update(_watch_play(group, nodes + ["recorder"], keep_going, _progress(listener, len(stamps))))
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
        print(("\r" + text + ("\n" if final else "")) if tty else text, end="" if tty else "\n", flush=True)

    return show


def _wait_wired(
    group: ProcessGroup,
    listener: ArrivalListener,
    cameras: Sequence[str],
    timeout_s: float,
    frontends: bool = True,
) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        dead = group.dead()
        if dead:
            raise DemoError(
                "process exited during start-up:\n  "
                + "\n  ".join(_crash_text(group.procs[n], c) for n, c in dead.items())
            )
        missing = missing_links(listener, cameras, frontends)
        if not missing:
            return
        if time.monotonic() > deadline:
            raise DemoError(f"graph not wired after {timeout_s:.0f} s: {'; '.join(missing)}")
        time.sleep(0.2)


def _watch_play(group: ProcessGroup, watched: list[str], keep_going: bool, progress=None) -> dict[str, str]:
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


def _check_crashes(
    group: ProcessGroup, watched: list[str], crashed: dict[str, str], keep_going: bool
) -> None:
    for name, code in group.dead(watched).items():
        if name not in crashed:
            crashed[name] = _crash_text(group.procs[name], code)
            if keep_going:
                log(f"NODE CRASHED (--keep-going: replay continues): {crashed[name]}")
            else:
                raise DemoError(
                    f"{name} crashed during the replay (use --keep-going to finish "
                    f"the replay anyway):\n  {crashed[name]}"
                )


def _drain(
    group: ProcessGroup,
    listener: ArrivalListener,
    stamps: Sequence[int],
    idle_s: float,
    nodes: list[str],
    crashed: dict[str, str],
    keep_going: bool,
) -> None:
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
