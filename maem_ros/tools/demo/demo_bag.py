"""The maem-demo bag: generating it (sim scene -> maem-make-bag), reading what the demo needs from
it, checking that the simulator still regenerates it, trimming it to the played frames."""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.core.interchange import SceneFolder
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.sim.scene import Scene, SceneConfig
from maem_ros.tools.bags import make_bag
from maem_ros.tools.eval.evaluate import to_sportcenter13
from maem_ros.tools.simulate import gt_arrays
from maem_ros.wire import msg_to_poses

REPO_ROOT = Path(__file__).resolve().parents[3]
#: the committed demo bag's scene (maem-demo --make-bag)
DEMO_SCENE: dict[str, Any] = {
    "rig": "sportcenter6",
    "frames": 30,
    "fps": 30.0,
    "seed": 0,
    "difficulty": "medium",
    "num_vertices": 18439,
    "players": 10,
    "bystanders": 2,
    "start_stamp_ns": 1_700_000_000_000_000_000,
}
#: demo bag size knobs: JPEG quality of the rendered images, mesh vertices kept per detection
JPEG_QUALITY = 35
BAG_VERTICES = 256


def log(text: str) -> None:
    print(f"maem-demo: {text}", flush=True)


def default_bag() -> Path:
    """bags/demo of the source checkout when there is one, else ./bags/demo."""
    repo = REPO_ROOT / "bags"
    return (repo if repo.is_dir() else Path("bags")) / "demo"


def image_topic(cam: str) -> str:
    return f"/{cam}/image_raw/compressed"


# ---------------------------------------------------------------------------------------------
# generating
# ---------------------------------------------------------------------------------------------
def subset_outputs(outputs: list[dict], idx: np.ndarray | None) -> list[dict]:
    """MAEM output dicts with only the mesh vertices ``idx`` (None = all)."""
    if idx is None:
        return outputs
    keys = ("pred_keypoints_2d_verts", "pred_vertices")
    return [{k: (np.ascontiguousarray(v[idx]) if k in keys else v) for k, v in o.items()} for o in outputs]


def write_demo_scene(root: Path, scene_config: dict, quality: int, vertices: int) -> Path:
    """Scene folder (maem-sim layout) of ``scene_config``: raw JPEGs at ``quality``, npz with an
    evenly spaced subset of ``vertices`` mesh vertices, gt.npz, scene.json (full config)."""
    scene = Scene(SceneConfig.from_dict(scene_config))
    n = scene.num_frames
    info = {
        "fps": float(scene.fps),
        "start_stamp_ns": int(scene.stamp_ns(0)),
        "num_frames": n,
        "scene_config": scene.config.to_dict(),
    }
    folder = SceneFolder.create(root, scene.rig, info)
    idx = make_bag.vertex_subset(scene.config.num_vertices, vertices)
    for frame in range(n):
        for cam in scene.rig.names:
            folder.write_outputs(cam, frame, subset_outputs(scene.raw_outputs(cam, frame), idx))
            folder.write_image(cam, frame, scene.render(cam, frame), quality=quality)
    folder.write_gt(*gt_arrays(scene, n), convention=SPORTCENTER_13.name)
    return root


def make_demo_bag(
    out: Path,
    frames: int = DEMO_SCENE["frames"],
    seed: int = DEMO_SCENE["seed"],
    quality: int = JPEG_QUALITY,
    vertices: int = BAG_VERTICES,
) -> Path:
    """Build the demo bag at ``out`` (must not exist): sim scene -> maem-make-bag --compress."""
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


def ensure_bag(bag: Path | None, frames: int) -> Path:
    """The bag given with --bag (which must exist: it is never created here), or the default
    demo bag, generated (seeded) when missing. Whether a folder is a bag is bagio's call (a
    bag without metadata.yaml, as a killed recorder leaves, is one)."""
    if bag is not None:
        if not bag.exists():
            raise bagio.BagError(
                f"--bag {str(bag)!r}: no such file or directory (maem-demo --make-bag DIR builds a demo bag)"
            )
        bagio.bag_info(bag)  # BagError: not a rosbag2 folder / not MCAP / nothing complete
        return bag
    bag = default_bag()
    if not bag.exists():
        log(f"no bag at {str(bag)!r}: generating the demo bag (seeded)")
        make_demo_bag(bag, frames=frames)
    else:
        try:
            bagio.bag_info(bag)
        except bagio.BagError as e:
            raise bagio.BagError(f"default bag: {e}") from None
    return bag


# ---------------------------------------------------------------------------------------------
# reading, checking, trimming
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


def load_bag(path: Path) -> DemoBag:
    """Read a demo bag's metadata, image stamps and ground truth; ValueError when unusable."""
    info = bagio.bag_info(path)
    if info.damage:  # cut short by a crash: the demo runs on every complete frame
        log(f"warning: {info.damage}")
    cams = sorted(t.split("/")[1] for t in info.topics if t.endswith("/image_raw/compressed"))
    if not cams:
        raise ValueError(f"bag {str(path)!r}: no /<camera>/image_raw/compressed topic")
    rig_yaml = bagio.read_rig_yaml(path)
    if not rig_yaml:
        raise ValueError(f"bag {str(path)!r}: no rig in metadata custom_data ({bagio.CUSTOM_RIG})")
    stamps = sorted({m.log_time_ns for m in bagio.read_messages(path, [image_topic(cams[0])], info=info)})
    convention = info.custom.get(bagio.CUSTOM_GT_CONVENTION)
    gt = {}
    for m in bagio.read_messages(path, [bagio.GT_TOPIC], info=info):
        pf = msg_to_poses(m.decode(), bagio.GT_TOPIC)
        gt[pf.stamp_ns] = to_sportcenter13(pf.joints, convention)
    return DemoBag(path, info, cams, stamps, bagio.read_scene_config(path), rig_yaml, gt)


def check_scene(demo: DemoBag, tol_m: float = 1e-3) -> None:
    """ValueError when the simulator no longer regenerates the bag's ground truth (the bag was
    made by another simulator version: the synthetic frontends would see other people)."""
    if demo.scene_config is None or not demo.gt:
        return
    scene = Scene(SceneConfig.from_dict(demo.scene_config))
    stamp = min(demo.gt)
    frame = scene.frame_at(stamp)
    want = demo.gt[stamp]
    got = (
        SPORTCENTER_13.select(scene.gt_keypoints(frame)[scene.is_player])
        if frame is not None
        else np.zeros((0, SPORTCENTER_13.num_joints, 3))
    )
    ok = got.shape == want.shape and bool(np.nanmax(np.abs(got - want), initial=0.0) < tol_m)
    if not ok:
        raise ValueError(
            f"bag {str(demo.path)!r} was made by another simulator version: its "
            f"ground truth differs from the scene its description regenerates; "
            f"rebuild it with: maem-demo --make-bag {demo.path} (after removing it)"
        )


def trim_bag(src: DemoBag, dst: Path, frames: int) -> Path:
    """Copy the first ``frames`` frames of ``src`` (all topics, custom data, QoS) to ``dst``."""
    stop = src.stamps[frames] if frames < len(src.stamps) else src.info.end_ns + 1
    with bagio.BagWriter(dst, compress=False) as w:
        for key, value in src.info.custom.items():
            w.set_custom(key, value)
        for topic, msgtype in src.info.topics.items():
            qos = src.info.qos.get(topic)
            w.add_topic(topic, msgtype, qos[0] if qos else None)
        for m in bagio.read_messages(src.path, stop_ns=stop, info=src.info):
            w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns)
    return dst
