"""TF for the rig: world -> camera transforms (geometry), /tf_static from the association node
to another process (transient local, late joiner), and one log line when tf2_msgs is absent."""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maem_ros.core.geometry.frames import rig_transforms
from maem_ros.params import resolve_rig_path
from maem_ros.ros import wire

from helpers_ros import OutputWatcher, killed_on_exit, ros_node, wait_for

BIN = Path(sys.executable).parent


def test_rig_transforms_are_the_camera_poses() -> None:
    from maem_ros.core.geometry.camera import Rig
    rig = Rig.load(resolve_rig_path("sportcenter6"))
    transforms = rig_transforms(rig, "court")
    X = np.random.default_rng(0).uniform(-10, 10, (50, 3))
    for cam, t in zip(rig, transforms):
        assert (t.parent, t.child) == ("court", cam.name)
        np.testing.assert_allclose(t.translation, cam.center, atol=1e-12)
        assert np.linalg.norm(t.quaternion) == pytest.approx(1.0)
        # optical-frame points mapped by the transform land where they came from in the world
        np.testing.assert_allclose(t.apply(cam.world_to_camera(X)), X, atol=1e-9)


def test_tf_message_roundtrip_and_bad_quaternion() -> None:
    tf2 = pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built (make builds it)")
    from maem_ros.core.geometry.camera import Rig
    rig = Rig.load(resolve_rig_path("humanm3_4"))
    msg = wire.tf_message(rig_transforms(rig), 5_000_000_123)
    assert isinstance(msg, tf2.TFMessage) and len(msg.transforms) == len(rig)
    assert msg.transforms[0].header.stamp.sec == 5 and msg.transforms[0].header.stamp.nanosec == 123
    back = wire.msg_to_transforms(msg, "/tf_static")
    for a, b in zip(back, rig_transforms(rig)):
        np.testing.assert_allclose(a.translation, b.translation)
        np.testing.assert_allclose(a.quaternion, b.quaternion)
    msg.transforms[1].transform.rotation.w = 2.0
    with pytest.raises(wire.WireError, match="transforms\\[1\\].*non-unit quaternion"):
        wire.msg_to_transforms(msg, "/tf_static")


def _association(tmp_path: Path, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / "association"), "--ros-args", "-p", "rig:=sportcenter6"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=tmp_path, env=env)


@pytest.mark.ros
def test_tf_static_reaches_a_late_subscriber_in_another_process(tmp_path: Path) -> None:
    tf2 = pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built (make builds it)")
    from maem_ros.core.geometry.camera import Rig
    from maem_ros.ros.qos import TF_STATIC_QOS
    rig = Rig.load(resolve_rig_path("sportcenter6"))
    proc = _association(tmp_path)
    with killed_on_exit(proc):
        out = OutputWatcher(proc)
        assert out.wait_line("-> /maem/clusters", 120), out.text()  # published before this line
        with ros_node("tf_listener") as (node, ex):
            got = []
            node.create_subscription(tf2.TFMessage, "/tf_static", got.append, TF_STATIC_QOS)
            assert wait_for(lambda: bool(got), 30, ex), out.text()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    transforms = wire.msg_to_transforms(got[0], "/tf_static")
    assert [t.child for t in transforms] == rig.names
    for t, cam in zip(transforms, rig):
        assert t.parent == "world"
        np.testing.assert_allclose(t.translation, cam.center, atol=1e-9)


@pytest.mark.ros
def test_without_tf2_msgs_the_node_runs_and_says_tf_is_skipped(tmp_path: Path) -> None:
    """A machine where the tf2_msgs build was skipped: one clear line, the node works."""
    import os
    blocker = tmp_path / "blocker" / "tf2_msgs"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('tf2_msgs hidden by the test')\n")
    env = {**os.environ, "PYTHONPATH": f"{blocker.parent}:{os.environ.get('PYTHONPATH', '')}"}
    proc = _association(tmp_path, env)
    with killed_on_exit(proc):
        out = OutputWatcher(proc)
        assert out.wait_line("-> /maem/clusters", 120), out.text()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    skipped = [line for line in out.text().splitlines() if "TF skipped" in line]
    assert len(skipped) == 1 and "tf2_msgs is not importable" in skipped[0], out.text()


@pytest.mark.ros
def test_player_replays_tf_static_of_a_bag(tmp_path: Path) -> None:
    tf2 = pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built (make builds it)")
    from maem_ros import bagio
    from maem_ros.core.geometry.camera import Rig
    from maem_ros.ros.qos import TF_STATIC_QOS
    rig = Rig.load(resolve_rig_path("humanm3_3"))
    t0 = 1_700_000_000_000_000_000
    bag = tmp_path / "bag"
    with bagio.BagWriter(bag) as w:
        w.write(wire.TF_STATIC_TOPIC, wire.tf_message(rig_transforms(rig), t0,
                                                      bagio.TYPESTORE.types), t0, bagio.QOS_LATCHED)
        for i in range(3):
            w.write("/t1", bagio.string_msg(f"a{i}"), t0 + i * 10_000_000)
    with ros_node("tf_bag_listener") as (node, ex):
        got = []
        node.create_subscription(tf2.TFMessage, "/tf_static", got.append, TF_STATIC_QOS)
        proc = subprocess.Popen([str(BIN / "player"), str(bag), "--wait-subscribers", "8"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        with killed_on_exit(proc):
            assert wait_for(lambda: bool(got), 30, ex), proc.poll()
            out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, out
    transforms = wire.msg_to_transforms(got[0], "/tf_static")
    assert [t.child for t in transforms] == rig.names
    np.testing.assert_allclose(transforms[2].translation, rig[rig.names[2]].center, atol=1e-9)
