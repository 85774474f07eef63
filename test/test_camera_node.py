"""maem-camera: sources, reconnect/backoff logic, and the node end to end (subprocess + subscriber)."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from maem_ros.capture import Capture, ImageFolderSource, VideoSource, make_source
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.ros.qos import IMAGE_QOS
from maem_ros.ros.wire import camera_info_msg

from helpers_ros import ros_node

# every test runs the camera node
pytestmark = pytest.mark.ros

W, H = 160, 120
LEVELS = [20 * i + 10 for i in range(10)]  # frame i is uniformly LEVELS[i] grey


# ---------------------------------------------------------------------------------------------
# pure logic
# ---------------------------------------------------------------------------------------------
class FakeSource:
    """Scripted source: ``opens`` = results of successive open() calls; ``frames`` per session."""

    def __init__(self, opens, frames_per_session=3, finite=False):
        self.opens = list(opens)
        self.frames_per_session = frames_per_session
        self.finite = finite
        self.description = "fake source"
        self.left = 0
        self.open_calls = 0
        self.released = 0

    def open(self):
        self.open_calls += 1
        ok = self.opens.pop(0) if self.opens else True
        self.left = self.frames_per_session if ok else 0
        return ok

    def read(self):
        if self.left <= 0:
            return None, 0
        self.left -= 1
        return np.zeros((2, 2), np.uint8), 123

    def rewind(self):
        self.left = self.frames_per_session
        return True

    def release(self):
        self.released += 1


def test_never_opening_source_fails_after_open_attempts_with_backoff():
    src = FakeSource([False] * 10)
    cap = Capture(src, open_attempts=4, backoff=0.5, backoff_max=1.5)
    now, attempts_at = 0.0, []
    result = None
    while now < 20.0:
        calls = src.open_calls
        result = cap.poll(now)
        if src.open_calls > calls:
            attempts_at.append(now)
        if result.status == "failed":
            break
        now = round(now + 0.1, 3)
    assert result.status == "failed" and "after 4 attempts" in result.message
    assert np.allclose(np.diff(attempts_at), [0.5, 1.0, 1.5])  # doubled, capped
    assert cap.poll(now + 100).status == "failed"  # final
    assert cap.counters.open_failures == 4 and cap.counters.frames == 0


def test_live_source_reconnects_and_counts():
    src = FakeSource([True, False, False, True], frames_per_session=2)
    cap = Capture(src, open_attempts=1, backoff=1.0, backoff_max=8.0)
    statuses = [cap.poll(t).status for t in (0.0, 0.1, 0.2)]
    assert statuses == ["frame", "frame", "waiting"]  # read failed -> lost
    assert cap.poll(0.3).status == "waiting"  # reopen immediately: fails
    assert cap.poll(0.5).status == "waiting"  # backoff 1 s not over: no attempt
    assert src.open_calls == 2
    assert cap.poll(1.3).status == "waiting"  # 2nd reopen fails, next after 2 s
    assert cap.poll(3.2).status == "waiting" and src.open_calls == 3
    assert cap.poll(3.3).status == "frame"  # 3rd reopen succeeds
    c = cap.counters
    assert (c.opens, c.reconnects, c.open_failures, c.read_failures) == (2, 1, 2, 1)


def test_max_reconnects_gives_up():
    src = FakeSource([True] + [False] * 5, frames_per_session=1)
    cap = Capture(src, backoff=0.01, max_reconnects=2)
    out = [cap.poll(t).status for t in np.arange(0, 1, 0.1)]
    assert out[0] == "frame" and out[-1] == "failed"


def test_finite_source_ends_or_loops():
    src = FakeSource([True], frames_per_session=2, finite=True)
    cap = Capture(src, loop=False)
    assert [cap.poll(t).status for t in range(4)] == ["frame", "frame", "ended", "ended"]
    src = FakeSource([True], frames_per_session=2, finite=True)
    cap = Capture(src, loop=True)
    assert [cap.poll(t).status for t in range(5)] == ["frame"] * 5
    assert cap.counters.loops == 2 and cap.counters.read_failures == 0


def test_make_source_kinds(tmp_path):
    clock = lambda: 0  # noqa: E731
    assert isinstance(make_source("0", clock), VideoSource) and make_source("2", clock).spec == 2
    assert isinstance(make_source(str(tmp_path), clock), ImageFolderSource)
    assert isinstance(make_source(str(tmp_path / "*.jpg"), clock), ImageFolderSource)
    assert not make_source("rtsp://10.0.0.1/live", clock).finite
    assert make_source(str(tmp_path / "x.avi"), clock).finite
    with pytest.raises(ValueError, match="^empty; give a device index"):
        make_source("  ", clock)


def test_image_folder_natural_order_and_stamps(tmp_path):
    for name, level in (("f_10.png", 3), ("f_2.png", 2), ("f_1.png", 1), ("notes.txt", 0)):
        if name.endswith(".png"):
            cv2.imwrite(str(tmp_path / name), np.full((4, 4), level, np.uint8))
        else:
            (tmp_path / name).write_text("x")
    t = iter(range(100, 200))
    src = ImageFolderSource(str(tmp_path), lambda: next(t))
    assert src.open()
    got = [src.read() for _ in range(4)]
    assert [int(f[0, 0, 0]) for f, _ in got[:3]] == [1, 2, 3] and got[3][0] is None
    assert [s for _, s in got[:3]] == [100, 101, 102]
    assert not ImageFolderSource(str(tmp_path / "*.jpg"), lambda: 0).open()


def test_camera_info_from_rig():
    cam = _rig().cameras[0]
    msg = camera_info_msg(cam, 5, "cam0")
    assert (msg.header.stamp.nanosec, msg.header.frame_id) == (5, "cam0")
    assert (msg.width, msg.height, msg.distortion_model) == (W, H, "plumb_bob")
    assert np.allclose(msg.k, cam.K.ravel()) and np.allclose(msg.d, cam.D)
    assert np.allclose(np.reshape(msg.p, (3, 4))[:, :3], cam.K_rect)


# ---------------------------------------------------------------------------------------------
# node end to end
# ---------------------------------------------------------------------------------------------
def _rig() -> Rig:
    return Rig([Camera("cam0", [[110.0, 0, 79.5], [0, 111.0, 59.5], [0, 0, 1]], np.eye(3),
                       [0, 0, 5], W, H, "plumb_bob", [-0.1, 0.01, 0.001, 0.0, 0.0])])


@pytest.fixture()
def rig_file(tmp_path) -> Path:
    path = tmp_path / "rig.yaml"
    _rig().to_yaml(path)
    return path


def _frame(level: int) -> np.ndarray:
    img = np.full((H, W, 3), level, np.uint8)
    img[:10, :20] = (255, 0, 0)  # a blue corner: checks the channel order
    return img


@contextmanager
def _node_process(*params: str):
    cmd = [sys.executable, "-m", "maem_ros.ros.camera_node", "--ros-args"]
    for p in params:
        cmd += ["-p", p]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
        proc.stdout.close()
        proc.stderr.close()


def _collect(msg_type, topic: str, count: int, proc, timeout: float = 40.0):
    images, infos = [], []
    with ros_node("probe") as (node, ex):
        node.create_subscription(msg_type, topic, images.append, IMAGE_QOS)
        node.create_subscription(CameraInfo, "/cam0/camera_info", infos.append, IMAGE_QOS)
        deadline = time.monotonic() + timeout
        while (len(images) < count or not infos) and time.monotonic() < deadline:
            assert proc.poll() is None, f"node exited early: {proc.stderr.read()}"
            ex.spin_once(timeout_sec=0.1)
    assert len(images) >= count, f"only {len(images)} frames on {topic} in {timeout} s"
    return images, infos


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _check_sequence(frames: list[np.ndarray], stamps: list[int], fps: float) -> None:
    assert all(f.shape == (H, W, 3) for f in frames)
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "stamps must increase"
    dt = np.median(np.diff(stamps)) / 1e9
    assert 0.4 / fps < dt < 2.5 / fps, f"median frame period {dt:.3f} s at {fps} Hz"
    levels = [float(f[H // 2:, W // 2:].mean()) for f in frames]
    idx = [int(np.argmin([abs(lv - x) for x in LEVELS])) for lv in levels]
    assert all(abs(lv - LEVELS[i]) < 6 for lv, i in zip(levels, idx)), levels
    steps = [(b - a) % len(LEVELS) for a, b in zip(idx, idx[1:])]
    assert sum(s == 1 for s in steps) >= len(steps) - 2, f"frames out of order: {idx}"
    assert all(f[3, 3, 0] > 200 and f[3, 3, 2] < 60 for f in frames), "channel order not BGR"


def test_node_publishes_video_file_raw(tmp_path, rig_file):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for level in LEVELS:
        writer.write(_frame(level))
    writer.release()
    fps = 20.0
    with _node_process("camera:=cam0", f"rig:={rig_file}", f"source:={video}", f"fps:={fps}",
                       "loop:=true") as proc:
        msgs, infos = _collect(Image, "/cam0/image_raw", 12, proc)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    assert {m.encoding for m in msgs} == {"bgr8"} and {m.header.frame_id for m in msgs} == {"cam0"}
    frames = [np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width, 3) for m in msgs]
    _check_sequence(frames, [_stamp(m) for m in msgs], fps)
    cam = _rig().cameras[0]
    info = infos[-1]
    assert (info.width, info.height, info.header.frame_id) == (W, H, "cam0")
    assert np.allclose(info.k, cam.K.ravel()) and np.allclose(info.d, cam.D)
    assert _stamp(info) in {_stamp(m) for m in msgs} or _stamp(info) > _stamp(msgs[-1])


def test_node_publishes_image_folder_compressed(tmp_path, rig_file):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, level in enumerate(LEVELS):  # unpadded names: natural order matters
        cv2.imwrite(str(folder / f"frame_{i}.png"), _frame(level))
    fps = 15.0
    with _node_process("camera:=cam0", f"rig:={rig_file}", f"source:={folder}/*.png",
                       f"fps:={fps}", "loop:=true", "transport:=compressed",
                       "jpeg_quality:=95", "reliability:=best_effort") as proc:
        msgs, _ = _collect(CompressedImage, "/cam0/image_raw/compressed", 12, proc)
    assert {m.format for m in msgs} == {"bgr8; jpeg compressed bgr8"}
    frames = [cv2.imdecode(np.frombuffer(bytes(m.data), np.uint8), cv2.IMREAD_COLOR) for m in msgs]
    _check_sequence(frames, [_stamp(m) for m in msgs], fps)


def test_node_ends_cleanly_at_end_of_file(tmp_path, rig_file):
    folder = tmp_path / "few"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), _frame(LEVELS[i]))
    with _node_process("camera:=cam0", f"rig:={rig_file}", f"source:={folder}",
                       "fps:=30.0") as proc:
        assert proc.wait(timeout=30) == 0
        assert "end of image folder" in proc.stderr.read()


def test_source_that_never_opens_exits_2(tmp_path, rig_file):
    with _node_process("camera:=cam0", f"rig:={rig_file}", f"source:={tmp_path}/missing.avi",
                       "open_attempts:=3", "reconnect_backoff:=0.05") as proc:
        assert proc.wait(timeout=30) == 2
        err = proc.stderr.read()
    assert "cannot open video file" in err and "after 3 attempts" in err


def test_bad_parameters_exit_2(tmp_path, rig_file):
    with _node_process("camera:=nope", f"rig:={rig_file}", "source:=0") as proc:
        assert proc.wait(timeout=30) == 2
        err = proc.stderr.read()
    assert "parameter 'camera'" in err and "'nope' is not in rig" in err
    with _node_process("camera:=cam0", "source:=0", "fps:=-1.0") as proc:
        assert proc.wait(timeout=30) == 2
        assert "parameter 'fps'" in proc.stderr.read()


def test_unreadable_file_in_folder_is_skipped_not_replayed(tmp_path):
    """A corrupt image is counted and skipped; the folder is not reopened from the start."""
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((4, 4), i + 1, np.uint8))
    (tmp_path / "1.png").write_bytes(b"not an image")
    cap = Capture(ImageFolderSource(str(tmp_path), lambda: 0), loop=False)
    polls = [cap.poll(float(k)) for k in range(5)]
    assert [p.status for p in polls[:4]] == ["frame", "skipped", "frame", "ended"]
    assert [int(p.frame[0, 0, 0]) for p in polls if p.status == "frame"] == [1, 3]
    assert cap.counters.skipped == 1 and cap.counters.read_failures == 0
    assert "1.png" in polls[1].message
