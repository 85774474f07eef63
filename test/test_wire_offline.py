"""The offline decode path works without rclpy: a Python in which rclpy and the ROS message
packages cannot be imported reads the committed demo bag (bags/demo) with bagio and decodes its
detections, ground-truth poses and /tf_static with maem_ros.wire alone; the offline tools import
without them."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

from maem_ros import bagio
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.geometry.frames import rig_transforms

BAG = Path(__file__).resolve().parents[1] / "bags" / "demo"
#: what a machine without the ROS wheels lacks: rclpy and the generated message packages
BLOCKED = ("rclpy", "builtin_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs",
           "visualization_msgs", "tf2_msgs", "diagnostic_msgs", "rcl_interfaces")
#: modules an offline tool imports to read a bag
OFFLINE_MODULES = ("maem_ros.wire", "maem_ros.bagio")

_SCRIPT = """
import json, sys
for name in {blocked!r}:
    sys.modules[name] = None  # import name -> ImportError
try:
    import rclpy  # noqa: F401
    raise SystemExit("rclpy was importable: the block does not work")
except ImportError:
    pass
import importlib
for mod in {modules!r}:
    importlib.import_module(mod)
import numpy as np
from maem_ros import bagio, wire
out = {{"detections": {{}}, "poses": [], "tf": []}}
for m in bagio.read_messages({bag!r}):
    if m.topic.endswith("/detections"):
        d = wire.msg_to_detections(wire.cdr_to_cloud(m.data, m.topic), m.topic)
        out["detections"].setdefault(d.camera, []).append(
            [d.stamp_ns, d.n, d.num_joints, d.num_vertices,
             float(np.nansum(d.kpts2d)), float(np.nansum(d.verts2d))])
    elif m.topic == bagio.GT_TOPIC:
        p = wire.msg_to_poses(m.decode(), m.topic)
        out["poses"].append([p.stamp_ns, p.ids.tolist(), p.joints.tolist()])
    elif m.topic == wire.TF_STATIC_TOPIC:
        out["tf"] = [[t.parent, t.child, t.translation.tolist(), t.quaternion.tolist()]
                     for t in wire.msg_to_transforms(m.decode(), m.topic)]
out["rclpy_loaded"] = sys.modules.get("rclpy") is not None
print(json.dumps(out))
"""


def _decode_offline(modules: tuple[str, ...] = OFFLINE_MODULES) -> dict:
    script = _SCRIPT.format(blocked=BLOCKED, modules=modules, bag=str(BAG))
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_demo_bag_decodes_without_rclpy(tmp_path):
    out = _decode_offline()
    assert not out["rclpy_loaded"]
    info = bagio.bag_info(BAG)
    cams = sorted(t.split("/")[1] for t in info.topics if t.endswith("/detections"))
    assert sorted(out["detections"]) == cams
    gt_stamps = [p[0] for p in out["poses"]]
    assert len(gt_stamps) == info.counts[bagio.GT_TOPIC] > 0
    for cam, rows in out["detections"].items():
        assert len(rows) == info.counts[f"/{cam}/detections"]
        # one detections message per camera per frame, stamped at the frame's capture time
        assert [r[0] for r in rows] == gt_stamps
        assert all(r[1] > 0 and r[2] > 0 and r[3] > 0 and np.isfinite(r[4:]).all() for r in rows)
    people = len(out["poses"][0][1])
    for _stamp, ids, joints in out["poses"]:
        assert len(ids) == people and np.isfinite(np.asarray(joints, float)).any()
    # geometric ground truth: /tf_static places each camera where the bag's rig says it is
    (tmp_path / "rig.yaml").write_text(bagio.read_rig_yaml(BAG) or "")
    rig = Rig.load(tmp_path / "rig.yaml")
    want = {t.child: t for t in rig_transforms(rig, out["tf"][0][0])}
    assert sorted(want) == sorted(t[1] for t in out["tf"])
    for _parent, child, translation, quaternion in out["tf"]:
        np.testing.assert_allclose(translation, want[child].translation, atol=1e-9)
        q, w = np.asarray(quaternion), want[child].quaternion
        assert min(np.abs(q - w).max(), np.abs(q + w).max()) < 1e-9


#: offline tools: they read, write or decode bags and need no ROS wheels (tools/demo is not
#: among them: it runs the node graph)
OFFLINE_TOOLS = (
    "maem_ros.tools.bags.bag", "maem_ros.tools.bags.make_bag", "maem_ros.tools.eval.evaluate",
    "maem_ros.tools.eval.explain", "maem_ros.tools.export.export",
    "maem_ros.tools.export.foxglove_view", "maem_ros.tools.demo.demo_bag",
    "maem_ros.tools.demo.demo_metrics", "maem_ros.tools.demo.demo_report",
    "maem_ros.tools.demo.pose2sim_demo", "maem_ros.tools.calibrate.calibrate_board",
    "maem_ros.tools.calibrate.calibrate_people",
)


def test_offline_tools_import_without_rclpy():
    script = (f"import sys\nfor n in {BLOCKED!r}:\n    sys.modules[n] = None\n"
              f"import importlib\nfor m in {OFFLINE_TOOLS!r}:\n    importlib.import_module(m)\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
