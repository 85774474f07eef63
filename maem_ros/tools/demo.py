"""maem-demo: replay the demo bag through the real node graph; print accuracy, timing and latency.

    maem-demo [--bag bags/demo] [--out out/demo] [--frames N | --duration S] [--rate R]
              [--params config/demo.yaml] [--keep-going] [--no-graph]
    maem-demo --make-bag bags/demo        (regenerate the committed demo bag, seeded)

Graph mode (default) runs, each as its own process with one params file (OUT/params.yaml:
--params plus what the bag says, i.e. its rig and scene description, and association max_wait
1 s as the six frontends share the CPU): maem-record (/maem/poses, /maem/skeletons,
/diagnostics -> OUT/record), one maem-frontend per camera (synthetic backend on
/<cam>/image_raw/compressed: it regenerates the full-resolution detections of each image stamp
from the bag's scene description), maem-association, maem-triangulation, and last maem-play
(the bag without its recorded detections and ground truth, at --rate). At the end every process
gets SIGINT and its exit code is checked. --no-graph runs the core pipeline on the bag's
recorded (vertex-subset) detections in this process instead.

Printed: the maem-eval accuracy table against the bag's /maem/gt_poses (same metrics, see
maem-eval --help), per-stage timing from the last recorded /diagnostics of each node,
end-to-end latency and frames dropped. Written to OUT: report.json, snapshot_<cam>.png
(skeletons projected on a camera image), court.png (top-down view), logs/, record/.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from maem_ros.tools import bagio

REPO_ROOT = Path(__file__).resolve().parents[2]
#: the committed demo bag's scene (maem-demo --make-bag)
DEMO_SCENE = {"rig": "sportcenter6", "frames": 30, "fps": 30.0, "seed": 0, "difficulty": "medium",
              "num_vertices": 18439, "players": 10, "bystanders": 2,
              "start_stamp_ns": 1_700_000_000_000_000_000}
#: demo bag size knobs: JPEG quality of the rendered images, mesh vertices kept per detection
JPEG_QUALITY = 35
BAG_VERTICES = 256
#: default playback rate (1.5 fps): each synthetic frontend regenerates 18,439-vertex
#: detections of ~12 people per image (~55 ms CPU); all six get a frame at the same moment and
#: share 2 cores with the rest of the machine (0.2-0.4 s per frame here), so faster replays
#: drop frames
DEFAULT_RATE = 0.05
RECORD_TOPICS = ("/maem/poses", "/maem/skeletons", "/diagnostics")
LATENCY_DEFINITION = (
    "latency = wall time (monotonic clock of the demo's listener node) at which /maem/poses with "
    "stamp s is received, minus the wall time at which the listener received the first "
    "/<cam>/image_raw/compressed with stamp s from maem-play; both measured in one process, so "
    "it covers DDS transport, the frontends, synchronisation wait, association, triangulation")


def log(text: str) -> None:
    print(f"maem-demo: {text}", flush=True)


def default_bag() -> Path:
    """bags/demo of the source checkout when there is one, else ./bags/demo."""
    repo = REPO_ROOT / "bags"
    return (repo if repo.is_dir() else Path("bags")) / "demo"


# ---------------------------------------------------------------------------------------------
# the demo bag
# ---------------------------------------------------------------------------------------------
def subset_outputs(outputs: list[dict], idx: np.ndarray | None) -> list[dict]:
    """MAEM output dicts with only the mesh vertices ``idx`` (None = all)."""
    if idx is None:
        return outputs
    keys = ("pred_keypoints_2d_verts", "pred_vertices")
    return [{k: (np.ascontiguousarray(v[idx]) if k in keys else v) for k, v in o.items()}
            for o in outputs]


def write_demo_scene(root: Path, scene_config: dict, quality: int, vertices: int) -> Path:
    """Scene folder (maem-sim layout) of ``scene_config``: raw JPEGs at ``quality``, npz with an
    evenly spaced subset of ``vertices`` mesh vertices, gt.npz, scene.json (full config)."""
    from maem_ros.core.interchange import SceneFolder
    from maem_ros.core.skeleton import SPORTCENTER_13
    from maem_ros.sim.scene import Scene, SceneConfig
    from maem_ros.tools.make_bag import vertex_subset
    from maem_ros.tools.simulate import gt_arrays

    scene = Scene(SceneConfig.from_dict(scene_config))
    n = scene.num_frames
    info = {"fps": float(scene.fps), "start_stamp_ns": int(scene.stamp_ns(0)), "num_frames": n,
            "scene_config": scene.config.to_dict()}
    folder = SceneFolder.create(root, scene.rig, info)
    idx = vertex_subset(scene.config.num_vertices, vertices)
    for frame in range(n):
        for cam in scene.rig.names:
            folder.write_outputs(cam, frame, subset_outputs(scene.raw_outputs(cam, frame), idx))
            folder.write_image(cam, frame, scene.render(cam, frame), quality=quality)
    folder.write_gt(*gt_arrays(scene, n), convention=SPORTCENTER_13.name)
    return root


def make_demo_bag(out: Path, frames: int = DEMO_SCENE["frames"], seed: int = DEMO_SCENE["seed"],
                  quality: int = JPEG_QUALITY, vertices: int = BAG_VERTICES) -> Path:
    """Build the demo bag at ``out`` (must not exist): sim scene -> maem-make-bag --compress."""
    import tempfile

    from maem_ros.tools import make_bag
    if out.exists():
        raise ValueError(f"--make-bag {str(out)!r}: exists already; remove it first")
    cfg = dict(DEMO_SCENE, frames=int(frames), seed=int(seed))
    with tempfile.TemporaryDirectory(prefix="maem_demo_scene_") as tmp:
        t0 = time.monotonic()
        scene_dir = write_demo_scene(Path(tmp) / "scene", cfg, quality, vertices)
        log(f"simulated {frames} frames x 6 cameras in {time.monotonic() - t0:.1f} s")
        out.parent.mkdir(parents=True, exist_ok=True)
        code = make_bag.main([str(out), "--scene", str(scene_dir), "--compress", "--quiet"])
    if code != 0:
        raise RuntimeError(f"maem-make-bag failed with exit code {code}")
    size = sum(p.stat().st_size for p in out.iterdir())
    log(f"demo bag {str(out)!r}: {size / 1e6:.1f} MB")
    return out


# ---------------------------------------------------------------------------------------------
# reading the input bag
# ---------------------------------------------------------------------------------------------
@dataclass
class DemoBag:
    """What the demo needs from a bag: cameras, frame stamps, scene description, rig, GT."""

    path: Path
    info: bagio.BagInfo
    cameras: list[str]
    stamps: list[int]  # image stamps in order (one per frame)
    scene_config: dict | None
    rig_yaml: str
    gt: dict[int, np.ndarray]  # stamp -> (P,13,3) world m, NaN = masked joint

    @property
    def fps(self) -> float:
        d = np.diff(self.stamps)
        return float(1e9 / np.median(d)) if len(d) else float("nan")


def image_topic(cam: str) -> str:
    return f"/{cam}/image_raw/compressed"


def load_bag(path: Path) -> DemoBag:
    """Read a demo bag's metadata, image stamps and ground truth; ValueError when unusable."""
    from maem_ros.ros.wire import msg_to_poses
    from maem_ros.tools.evaluate import to_sportcenter13

    info = bagio.bag_info(path)
    cams = sorted(t.split("/")[1] for t in info.topics if t.endswith("/image_raw/compressed"))
    if not cams:
        raise ValueError(f"bag {str(path)!r}: no /<camera>/image_raw/compressed topic")
    rig_yaml = bagio.read_rig_yaml(path)
    if not rig_yaml:
        raise ValueError(f"bag {str(path)!r}: no rig in metadata custom_data ({bagio.CUSTOM_RIG})")
    stamps = sorted({m.log_time_ns for m in bagio.read_messages(path, [image_topic(cams[0])])})
    convention = info.custom.get(bagio.CUSTOM_GT_CONVENTION)
    gt = {}
    for m in bagio.read_messages(path, [bagio.GT_TOPIC]):
        pf = msg_to_poses(m.decode(), bagio.GT_TOPIC)
        gt[pf.stamp_ns] = to_sportcenter13(pf.joints, convention)
    return DemoBag(path, info, cams, stamps, bagio.read_scene_config(path), rig_yaml, gt)


def check_scene(demo: DemoBag, tol_m: float = 1e-3) -> None:
    """ValueError when the simulator no longer regenerates the bag's ground truth (the bag was
    made by another simulator version: the synthetic frontends would see other people)."""
    from maem_ros.core.skeleton import SPORTCENTER_13
    from maem_ros.sim.scene import Scene, SceneConfig
    if demo.scene_config is None or not demo.gt:
        return
    scene = Scene(SceneConfig.from_dict(demo.scene_config))
    stamp = min(demo.gt)
    frame = scene.frame_at(stamp)
    want = demo.gt[stamp]
    got = SPORTCENTER_13.select(scene.gt_keypoints(frame)[scene.is_player]) if frame is not None \
        else np.zeros((0, SPORTCENTER_13.num_joints, 3))
    ok = got.shape == want.shape and bool(np.nanmax(np.abs(got - want), initial=0.0) < tol_m)
    if not ok:
        raise ValueError(f"bag {str(demo.path)!r} was made by another simulator version: its "
                         f"ground truth differs from the scene its description regenerates; "
                         f"rebuild it with: maem-demo --make-bag {demo.path} (after removing it)")


def trim_bag(src: DemoBag, dst: Path, frames: int) -> Path:
    """Copy the first ``frames`` frames of ``src`` (all topics, custom data, QoS) to ``dst``."""
    stop = src.stamps[frames] if frames < len(src.stamps) else src.info.end_ns + 1
    with bagio.BagWriter(dst, compress=False) as w:
        for key, value in src.info.custom.items():
            w.set_custom(key, value)
        for topic, msgtype in src.info.topics.items():
            qos = src.info.qos.get(topic) or [None]
            w.add_topic(topic, msgtype, qos[0])
        for m in bagio.read_messages(src.path, stop_ns=stop):
            w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns)
    return dst


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
                 max_wait_s: float = 1.0) -> Path:
    """``base`` params file with the bag's rig for every node; for the frontends compressed
    images and the bag's scene description (the synthetic backend regenerates from it); for the
    association ``max_wait_s`` (s; the six frontends share the CPU, so one frame's detections
    arrive spread over a few hundred ms)."""
    from maem_ros.params import resolve_config_path
    data = yaml.safe_load(resolve_config_path(base).read_text()) or {}
    nodes = {name: node_section(data, name)
             for name in ("frontend", "association", "triangulation")}
    data.setdefault("/**", {}).setdefault("ros__parameters", {})["rig"] = str(rig_path)
    for section in nodes.values():
        if "rig" in section:
            section["rig"] = str(rig_path)
    fe = nodes["frontend"]
    fe["image_transport"] = "compressed"
    if fe.get("backend", "synthetic") == "synthetic":
        if scene_config is None:
            raise ValueError("the bag has no scene description (/maem/scene): the synthetic "
                             "frontend cannot regenerate its detections")
        fe.update(_SCENE_SENTINELS)
        fe["scene_dict"] = json.dumps(scene_config, sort_keys=True)
        fe["scene_rig"] = str(scene_config.get("rig", ""))
    nodes["association"]["max_wait"] = float(max_wait_s)
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


# ---------------------------------------------------------------------------------------------
# processes
# ---------------------------------------------------------------------------------------------
@dataclass
class Proc:
    name: str
    popen: subprocess.Popen
    log: Path

    def tail(self, chars: int = 1500) -> str:
        try:
            return self.log.read_text(errors="replace")[-chars:]
        except OSError:
            return ""


@dataclass
class ProcessGroup:
    """Child processes with logs in ``log_dir``; ``stop`` sends SIGINT and collects exit codes."""

    log_dir: Path
    env: dict[str, str]
    procs: dict[str, Proc] = field(default_factory=dict)

    def start(self, name: str, cmd: Sequence[str]) -> Proc:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        with open(log_path, "wb") as fh:
            popen = subprocess.Popen(list(cmd), stdout=fh, stderr=subprocess.STDOUT, env=self.env,
                                     stdin=subprocess.DEVNULL)
        self.procs[name] = Proc(name, popen, log_path)
        return self.procs[name]

    def dead(self, names: Sequence[str] | None = None) -> dict[str, int]:
        """{name: exit code} of the processes (of ``names``) that have exited."""
        return {n: p.popen.returncode for n, p in self.procs.items()
                if (names is None or n in names) and p.popen.poll() is not None}

    def stop(self, names: Sequence[str], timeout_s: float = 10.0) -> dict[str, int | None]:
        """SIGINT ``names`` (still running), wait; kill leftovers. Exit codes, None = killed."""
        for n in names:
            if self.procs[n].popen.poll() is None:
                self.procs[n].popen.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        codes: dict[str, int | None] = {}
        for n in names:
            p = self.procs[n].popen
            try:
                codes[n] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=5)
                codes[n] = None
        return codes

    def shutdown(self) -> None:
        """SIGINT whatever still runs (recorder last, so it keeps what it received), then kill."""
        running = [n for n, p in self.procs.items() if p.popen.poll() is None]
        if running:
            self.stop([n for n in running if n != "recorder"], timeout_s=5.0)
            if "recorder" in running:
                self.stop(["recorder"], timeout_s=10.0)


def module_command(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


def child_env() -> dict[str, str]:
    """Environment of the children: a private random ROS_DOMAIN_ID unless the user set one, and
    localhost-only discovery, so two demos (or a demo and a test run) never hear each other."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


# ---------------------------------------------------------------------------------------------
# listener: image and poses arrival times (latency)
# ---------------------------------------------------------------------------------------------
def cdr_header_stamp_ns(data: bytes) -> int:
    """Header stamp of a serialized message whose first field is std_msgs/Header (CDR)."""
    if len(data) < 12:
        raise ValueError(f"serialized message: {len(data)} bytes, too short for a header")
    endian = "<" if data[1] & 1 else ">"
    sec, nsec = struct.unpack_from(endian + "iI", data, 4)
    return sec * 1_000_000_000 + nsec


class Listener:
    """rclpy node in its own context and thread: first arrival (monotonic ns) of each image stamp
    and of each /maem/poses stamp; also checks that the graph is wired before playing."""

    def __init__(self, cameras: Sequence[str], domain_id: int):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CompressedImage, PointCloud2

        from maem_ros.ros.common import DATA_QOS, IMAGE_QOS

        self.cameras = list(cameras)
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("maem_demo_listener", context=self.context)
        self.lock = threading.Lock()
        self.image_t: dict[int, int] = {}
        self.poses_t: dict[int, int] = {}
        self.subs = [self.node.create_subscription(CompressedImage, image_topic(c), self._on_image,
                                                   IMAGE_QOS, raw=True) for c in self.cameras]
        self.subs.append(self.node.create_subscription(PointCloud2, "/maem/poses", self._on_poses,
                                                       DATA_QOS, raw=True))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def _on_image(self, data: bytes) -> None:
        t = time.monotonic_ns()
        with self.lock:
            self.image_t.setdefault(cdr_header_stamp_ns(data), t)

    def _on_poses(self, data: bytes) -> None:
        t = time.monotonic_ns()
        with self.lock:
            self.poses_t.setdefault(cdr_header_stamp_ns(data), t)

    def missing_links(self) -> list[str]:
        """What is not wired yet (empty = frontends, association, triangulation, recorder ready)."""
        n = self.node
        need = [(image_topic(c), 2, "frontend") for c in self.cameras]
        need += [(f"/{c}/detections", 1, "association") for c in self.cameras]
        need += [("/maem/clusters", 1, "triangulation"), ("/maem/poses", 2, "recorder"),
                 ("/maem/skeletons", 1, "recorder"), ("/diagnostics", 1, "recorder")]
        return [f"{topic} has no {who} subscriber" for topic, k, who in need
                if n.count_subscribers(topic) < k]

    def snapshot(self) -> tuple[dict[int, int], dict[int, int]]:
        with self.lock:
            return dict(self.image_t), dict(self.poses_t)

    def close(self) -> None:
        import rclpy
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


# ---------------------------------------------------------------------------------------------
# graph run
# ---------------------------------------------------------------------------------------------
@dataclass
class GraphRun:
    """Outcome of one graph replay."""

    exit_codes: dict[str, int | None]
    crashed: dict[str, str]  # process -> what happened (+ log tail)
    image_t: dict[int, int]
    poses_t: dict[int, int]
    wall_s: float
    record: Path


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
              drain_s: float = 5.0) -> GraphRun:
    """Start recorder + nodes, wait until wired, play ``bag`` (whose frames are ``stamps``),
    wait until every frame has poses (or none came for ``drain_s``), SIGINT everything."""
    warm_numba_cache()
    group = ProcessGroup(out / "logs", child_env())
    record = out / "record"
    nodes = [f"frontend_{c}" for c in demo.cameras] + ["association", "triangulation"]
    listener = None
    crashed: dict[str, str] = {}
    try:
        group.start("recorder", module_command("maem_ros.ros.recorder_node", str(record),
                                               "--topics", *RECORD_TOPICS))
        for c in demo.cameras:
            group.start(f"frontend_{c}", module_command(
                "maem_ros.ros.frontend_node", "--ros-args", "--params-file", str(params),
                "-r", f"__ns:=/{c}"))
        for kind in ("association", "triangulation"):
            group.start(kind, module_command(f"maem_ros.ros.{kind}_node", "--ros-args",
                                             "--params-file", str(params)))
        # the listener (this process) joins the children's domain and discovery range
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE",
                              group.env["ROS_AUTOMATIC_DISCOVERY_RANGE"])
        listener = Listener(demo.cameras, int(group.env["ROS_DOMAIN_ID"]))
        _wait_wired(group, listener, startup_timeout_s)
        t0 = time.monotonic()
        group.start("player", module_command(
            "maem_ros.ros.player_node", str(bag), "--rate", f"{rate:g}", "--delay", "1.0",
            "--exclude", "/*/detections", bagio.GT_TOPIC))
        crashed.update(_watch_play(group, nodes + ["recorder"], keep_going))
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
    """Compile the epipolar kernels here (numba's on-disk cache) so the association node loads
    them at its first frame instead of compiling them for seconds while frames queue up."""
    from maem_ros.core import epipolar
    t0 = time.monotonic()
    epipolar.warmup()
    dt = time.monotonic() - t0
    if dt > 1.0:
        log(f"compiled the epipolar kernels in {dt:.1f} s (cached for the nodes)")


def _wait_wired(group: ProcessGroup, listener: Listener, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        dead = group.dead()
        if dead:
            raise DemoError("process exited during start-up:\n  " + "\n  ".join(
                _crash_text(group.procs[n], c) for n, c in dead.items()))
        missing = listener.missing_links()
        if not missing:
            return
        if time.monotonic() > deadline:
            raise DemoError(f"graph not wired after {timeout_s:.0f} s: {'; '.join(missing)}")
        time.sleep(0.2)


def _watch_play(group: ProcessGroup, watched: list[str], keep_going: bool) -> dict[str, str]:
    """Wait for the player to finish; a crashed node aborts unless ``keep_going``."""
    crashed: dict[str, str] = {}
    player = group.procs["player"].popen
    while player.poll() is None:
        _check_crashes(group, watched, crashed, keep_going)
        time.sleep(0.1)
    _check_crashes(group, watched, crashed, keep_going)
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


def _drain(group: ProcessGroup, listener: Listener, stamps: list[int], idle_s: float,
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
# results
# ---------------------------------------------------------------------------------------------
def recorded_poses(record: Path) -> dict[int, Any]:
    """stamp -> PoseFrame of the recorded /maem/poses (first message per stamp)."""
    from maem_ros.ros.wire import msg_to_poses
    out: dict[int, Any] = {}
    if not (record / "metadata.yaml").is_file():
        return out
    for m in bagio.read_messages(record, ["/maem/poses"]):
        pf = msg_to_poses(m.decode(), m.topic)
        out.setdefault(pf.stamp_ns, pf)
    return out


def recorded_diagnostics(record: Path) -> dict[str, dict[str, str]]:
    """node name -> key/values of its last recorded DiagnosticStatus."""
    out: dict[str, dict[str, str]] = {}
    if not (record / "metadata.yaml").is_file():
        return out
    for m in bagio.read_messages(record, ["/diagnostics"]):
        for st in m.decode().status:
            out[st.name] = {kv.key: kv.value for kv in st.values}
    return out


def score(demo: DemoBag, stamps: Sequence[int], preds: dict[int, tuple[np.ndarray, np.ndarray]]
          ) -> dict[str, Any]:
    """maem-eval metrics over ``stamps``; a frame without predictions counts as all missed."""
    from maem_ros.core.metrics import evaluate_sequence
    from maem_ros.core.skeleton import SPORTCENTER_13
    empty = (np.zeros((0, SPORTCENTER_13.num_joints, 3)), np.zeros(0))
    ps, ss, gts, masks = [], [], [], []
    for s in stamps:
        if s not in demo.gt:
            continue
        joints, scores = preds.get(s, empty)
        keep = np.isfinite(joints).all(-1).any(-1)
        ps.append(joints[keep])
        ss.append(scores[keep])
        g = demo.gt[s]
        m = np.isfinite(g).all(-1)
        gts.append(np.where(m[..., None], g, 0.0))
        masks.append(m)
    if not gts:
        raise ValueError(f"bag {str(demo.path)!r}: no ground truth (/maem/gt_poses) for the "
                         "played frames")
    metrics = dict(evaluate_sequence(ps, ss, gts, masks))
    metrics["frames"] = len(gts)
    return metrics


def stage_timing(diags: dict[str, dict[str, str]]) -> list[tuple[str, str, float, float, int, int]]:
    """Rows (node, stage, median ms, p99 ms, processed, dropped); frontends merged into one row
    per stage (median of the cameras' medians, max of their p99)."""
    groups: dict[str, list[dict[str, str]]] = {}
    for name, kv in sorted(diags.items()):
        key = "frontend" if name.endswith("/frontend") else name.strip("/")
        groups.setdefault(key, []).append(kv)
    rows = []
    for key, kvs in groups.items():
        label = f"{key} (x{len(kvs)})" if len(kvs) > 1 else key
        processed = sum(int(kv.get("frames_processed", 0)) for kv in kvs)
        dropped = sum(int(kv.get("frames_dropped", 0)) for kv in kvs)
        stages = sorted({k.split("/")[1] for kv in kvs for k in kv if k.startswith("time_ms/")})
        for st in stages:
            med = [float(kv[f"time_ms/{st}/median"]) for kv in kvs if f"time_ms/{st}/median" in kv]
            p99 = [float(kv[f"time_ms/{st}/p99"]) for kv in kvs if f"time_ms/{st}/p99" in kv]
            rows.append((label, st, float(np.median(med)), float(np.max(p99)), processed, dropped))
    return rows


def format_timing(rows) -> str:
    head = ("node", "stage", "median ms", "p99 ms", "processed", "dropped")
    body = [(n, s, f"{m:.2f}", f"{p:.2f}", str(a), str(d)) for n, s, m, p, a, d in rows]
    widths = [max(len(r[i]) for r in [head] + body) for i in range(len(head))]
    fmt = lambda r: "  ".join(c.ljust(w) if i < 2 else c.rjust(w)  # noqa: E731
                              for i, (c, w) in enumerate(zip(r, widths)))
    return "\n".join([fmt(head), "  ".join("-" * w for w in widths)] + [fmt(r) for r in body])


def latencies_ms(image_t: dict[int, int], poses_t: dict[int, int]) -> np.ndarray:
    return np.array([(poses_t[s] - t) / 1e6 for s, t in image_t.items() if s in poses_t])


def dropped_counters(diags: dict[str, dict[str, str]]) -> dict[str, dict[str, str]]:
    """Per node: its non-zero drop / missing-camera counters."""
    out = {}
    for name, kv in diags.items():
        d = {k: v for k, v in kv.items()
             if (k.startswith(("dropped/", "missing/")) or k == "frames_dropped") and v != "0"}
        if d:
            out[name] = d
    return out


# ---------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------
def snapshot_png(path: Path, demo: DemoBag, rig, cam: str, stamp: int, pred: Any) -> Path:
    """Raw camera image at ``stamp`` with GT (white) and estimated skeletons (colour = track id)
    projected through the camera's distortion."""
    import cv2

    from maem_ros.core.skeleton import SPORTCENTER_13
    from maem_ros.frontend.overlay import colour_for
    from maem_ros.ros.wire import UNTRACKED_ID
    msg = next(bagio.read_messages(demo.path, [image_topic(cam)], start_ns=stamp,
                                   stop_ns=stamp + 1)).decode()
    img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
    camera = rig[cam]

    def draw(joints: np.ndarray, colour, thick: int, label: str | None) -> None:
        uv = camera.project(joints)
        ok = np.isfinite(uv).all(-1)
        for a, b in SPORTCENTER_13.bones:
            if ok[a] and ok[b]:
                cv2.line(img, tuple(int(v) for v in uv[a]), tuple(int(v) for v in uv[b]), colour,
                         thick, cv2.LINE_AA)
        if label and ok.any():
            top = uv[ok][np.argmin(uv[ok][:, 1])]
            cv2.putText(img, label, (int(top[0]) - 10, int(top[1]) - 10),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)

    for g in demo.gt.get(stamp, []):
        draw(g, (255, 255, 255), 4, None)
    for pid, joints in zip(pred.ids, pred.joints):
        tracked = int(pid) != UNTRACKED_ID
        draw(joints, colour_for(int(pid)) if tracked else (128, 128, 128), 2,
             f"#{int(pid)}" if tracked else None)
    title = f"{cam}  stamp {stamp}  white = ground truth, colour = /maem/poses (track id)"
    (tw, th), _ = cv2.getTextSize(title, cv2.FONT_HERSHEY_SIMPLEX, 0.8, 2)
    cv2.rectangle(img, (10, 10), (30 + tw, 30 + th), (0, 0, 0), cv2.FILLED)
    cv2.putText(img, title, (20, 20 + th), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2,
                cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise ValueError(f"snapshot {str(path)!r}: cv2.imwrite failed")
    return path


def write_pictures(out: Path, demo: DemoBag, rig, stamps: Sequence[int], poses: dict[int, Any]
                   ) -> list[Path]:
    """snapshot_<cam>.png and court.png at the middle played frame that has poses."""
    from maem_ros.tools.plots import plot_court
    with_poses = [s for s in stamps if s in poses and s in demo.gt]
    if not with_poses:
        return []
    stamp = with_poses[len(with_poses) // 2]
    pred = poses[stamp]
    cam = demo.cameras[0]
    frame = demo.stamps.index(stamp)
    return [snapshot_png(out / f"snapshot_{cam}.png", demo, rig, cam, stamp, pred),
            plot_court(out / "court.png", frame, demo.gt[stamp], pred.joints, rig)]


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
    from maem_ros.core.association import associate
    from maem_ros.core.triangulation import triangulate
    from maem_ros.ros.wire import msg_to_detections
    from maem_ros.tools.evaluate import load_params, to_sportcenter13
    assoc, tri = load_params(params)
    frames: dict[int, dict[str, Any]] = {s: {} for s in stamps}
    topics = [f"/{c}/detections" for c in demo.cameras]
    if not any(t in demo.info.topics for t in topics):
        raise ValueError(f"bag {str(demo.path)!r}: no /<camera>/detections to run --no-graph on")
    stop = stamps[-1] + 1 if stamps else None
    for m in bagio.read_messages(demo.path, topics, stop_ns=stop):
        dets = msg_to_detections(m.decode(), m.topic, rig.names)
        if dets.stamp_ns in frames:
            frames[dets.stamp_ns][dets.camera] = dets
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
                   help="input bag (default bags/demo; generated first when missing)")
    p.add_argument("--out", type=Path, default=Path("out/demo"),
                   help="output folder (default out/demo)")
    p.add_argument("--params", default="demo.yaml", help="params file (default config/demo.yaml)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frames", type=int, default=None, help="play only the first N frames")
    g.add_argument("--duration", type=float, default=None, metavar="S",
                   help="play only the first S seconds of bag time")
    p.add_argument("--rate", type=float, default=DEFAULT_RATE,
                   help=f"playback rate (default {DEFAULT_RATE}; the bag is 30 fps)")
    p.add_argument("--keep-going", action="store_true",
                   help="finish the replay when a node crashes (reported at the end, exit 1)")
    p.add_argument("--no-graph", action="store_true",
                   help="offline: core association + triangulation on the bag's recorded "
                   "detections")
    p.add_argument("--startup-timeout", type=float, default=60.0, metavar="S",
                   help="give up when the graph is not wired after S seconds (default 60)")
    p.add_argument("--make-bag", type=Path, default=None, metavar="DIR",
                   help="only build the demo bag into DIR (seeded) and exit")
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


def print_accuracy(name: str, metrics: dict[str, Any]) -> None:
    from maem_ros.tools.evaluate import format_table
    print("\naccuracy against the bag's ground truth (/maem/gt_poses, players, sportcenter_13):")
    print(format_table([(name, metrics)]))


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.make_bag is not None:
        try:
            make_demo_bag(a.make_bag, frames=a.bag_frames)
        except (ValueError, RuntimeError) as e:
            print(f"maem-demo: {e}", file=sys.stderr)
            return 2
        return 0
    if not a.rate > 0:
        print(f"maem-demo: --rate must be > 0, got {a.rate}", file=sys.stderr)
        return 2
    if (a.frames is not None and a.frames < 1) or (a.duration is not None and a.duration <= 0):
        print("maem-demo: --frames / --duration must be positive", file=sys.stderr)
        return 2
    t_start = time.monotonic()
    try:
        return run_demo(a, t_start)
    except (ValueError, DemoError) as e:
        print(f"maem-demo: {e}", file=sys.stderr)
        return 1


def ensure_bag(bag: Path, frames: int) -> Path:
    """``bag`` when it is a rosbag2 folder; generate the demo bag there when it is missing."""
    if not (bag / "metadata.yaml").is_file():
        if bag.exists():
            raise ValueError(f"--bag {str(bag)!r}: not a rosbag2 folder (no metadata.yaml)")
        log(f"no bag at {str(bag)!r}: generating the demo bag (seeded)")
        make_demo_bag(bag, frames=frames)
    return bag


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
    check_scene(demo)
    n = len(stamps)
    play_bag = demo.path if n == len(demo.stamps) else trim_bag(demo, a.out / "input", n)
    params = write_params(a.params, a.out / "params.yaml", rig_path.resolve(), demo.scene_config)
    run = run_graph(play_bag, demo, stamps, params, a.out, a.rate, a.keep_going,
                    startup_timeout_s=a.startup_timeout)
    poses = recorded_poses(run.record)
    diags = recorded_diagnostics(run.record)
    metrics = score(demo, stamps, {s: (p.joints, p.scores) for s, p in poses.items()})
    assoc = next((kv for name, kv in diags.items() if name.strip("/") == "association"), {})
    metrics["association_ms_median"] = float(assoc.get("time_ms/associate/median", "nan"))
    print_accuracy("graph (maem-play -> nodes)", metrics)
    rows = stage_timing(diags)
    print("\nper-stage timing (last /diagnostics of each node, over its last <= 200 frames):")
    print(format_timing(rows) if rows else "  no /diagnostics recorded")
    lat = latencies_ms(run.image_t, run.poses_t)
    dropped = [s for s in stamps if s not in poses]
    print_run_summary(a.rate, n, lat, dropped, diags, run)
    report = {"metrics": metrics, "latency_definition": LATENCY_DEFINITION,
              "timing": [dict(zip(("node", "stage", "median_ms", "p99_ms", "processed",
                                   "dropped"), r)) for r in rows],
              "latency_ms_median": float(np.median(lat)) if len(lat) else None,
              "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
              "frames_dropped": len(dropped), "exit_codes": run.exit_codes,
              "crashed": run.crashed, "record": str(run.record), "replay_wall_s": run.wall_s}
    if run.crashed:
        print("\nNODE FAILURES:")
        for text in run.crashed.values():
            print(f"  {text}")
    return (1 if run.crashed else 0), poses, report


def print_run_summary(rate: float, n: int, lat: np.ndarray, dropped: list[int],
                      diags: dict[str, dict[str, str]], run: GraphRun) -> None:
    """Latency, dropped frames (and the nodes' drop counters), machine load, exit codes."""
    print(f"\nend-to-end latency (image received -> /maem/poses received, {len(lat)} frames): "
          + (f"median {np.median(lat):.0f} ms, p99 {np.percentile(lat, 99):.0f} ms, "
             f"max {lat.max():.0f} ms" if len(lat) else "no frame completed"))
    print(f"frames dropped: {len(dropped)} of {n} played frames have no /maem/poses"
          + (f" (rate {rate:g}; try a lower --rate)" if dropped and not run.crashed else ""))
    for name, d in sorted(dropped_counters(diags).items()):
        print(f"  {name}: " + ", ".join(f"{k}={v}" for k, v in sorted(d.items())))
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} "
          f"(1 min, all users)")
    print(f"replay wall time: {run.wall_s:.1f} s; processes: " + ", ".join(
        f"{k}={'killed' if v is None else v}" for k, v in run.exit_codes.items()))


def run_demo(a: argparse.Namespace, t_start: float) -> int:
    from maem_ros.core.camera import Rig
    from maem_ros.tools.evaluate import _jsonable
    bag = ensure_bag(a.bag or default_bag(), a.bag_frames)
    prepare_out(a.out)
    demo = load_bag(bag)
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
    report = {"bag": str(bag), "frames_played": len(stamps), "cameras": demo.cameras,
              "mode": "offline" if a.no_graph else "graph", "rate": a.rate, **entries,
              "pictures": [str(p) for p in pictures], "wall_s": time.monotonic() - t_start}
    (a.out / "report.json").write_text(json.dumps(_jsonable(report), indent=2))
    print(f"\nwrote {', '.join(str(p) for p in pictures) or 'no pictures (no frame with poses)'}, "
          f"{a.out / 'report.json'}")
    log(f"done in {report['wall_s']:.1f} s")
    return code


if __name__ == "__main__":
    sys.exit(main())
