"""maem-play: order and timing at rate 1 and 2, loop, topic filter, remap, start offset, /clock."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from maem_ros import bagio
from maem_ros.ros.player_node import BagPlayer, PlayOptions, loop_gap_ns, parse_args, select_topics

from helpers_ros import LATCHED, RELIABLE, killed_on_exit, ros_node, wait_for

# every test runs the player node
pytestmark = pytest.mark.ros

T0 = 1_700_000_000_000_000_000
# irregular spacing (s) on /t1; /t2 interleaved 10 ms after each /t1 message
OFFSETS = [0.0, 0.1, 0.25, 0.3, 0.5, 0.55, 0.8]


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("player") / "bag"
    with bagio.BagWriter(path) as w:
        w.write(bagio.SCENE_TOPIC, bagio.string_msg('{"seed": 3}'), T0, bagio.QOS_LATCHED)
        for i, off in enumerate(OFFSETS):
            t = T0 + int(off * 1e9)
            w.write("/t1", bagio.string_msg(f"a{i}"), t)
            w.write("/t2", bagio.string_msg(f"b{i}"), t + 10_000_000)
    return path


@pytest.fixture
def ros():
    with ros_node("player_test") as (node, ex):
        yield node, ex


def collect(node, topics, qos=RELIABLE):
    """Subscribe; returns {topic: [(monotonic arrival s, data)]}."""
    got = {t: [] for t in topics}
    for t in topics:
        cls = Clock if t == "/clock" else String
        node.create_subscription(cls, t, lambda m, t=t: got[t].append((time.monotonic(), m)), qos)
    return got


def test_parse_args_and_loop_gap(bag: Path):
    o = parse_args([str(bag), "--rate", "2", "--loop", "--topics", "/t1", "--remap", "/t1:=/x",
                    "--clock", "--start", "0.2"])
    assert (o.rate, o.loop, o.topics, o.remap, o.clock, o.clock_hz, o.start_s) == (
        2.0, True, ["/t1"], {"/t1": "/x"}, True, 40.0, 0.2)
    with pytest.raises(SystemExit):
        parse_args([str(bag), "--rate", "0"])
    with pytest.raises(SystemExit):
        parse_args([str(bag), "--remap", "nonsense"])
    info = bagio.bag_info(bag)
    assert loop_gap_ns(info) == (info.end_ns - info.start_ns) // (len(OFFSETS) - 1)


def test_select_topics_patterns():
    bag_topics = ["/maem/scene", "/c0/image_raw/compressed", "/c0/detections", "/c1/detections",
                  "/c1/camera_info"]
    assert select_topics(bag_topics, None) == (bag_topics, [])
    assert select_topics(bag_topics, None, ["/*/detections"]) == (
        ["/maem/scene", "/c0/image_raw/compressed", "/c1/camera_info"], [])
    assert select_topics(bag_topics, ["/c1/*", "/nope"]) == (["/c1/detections", "/c1/camera_info"],
                                                             ["/nope"])
    assert select_topics(bag_topics, ["/c0/detections"]) == (["/c0/detections"], [])


@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_timing_and_order(bag: Path, ros, rate: float):
    node, ex = ros
    got = collect(node, ["/t1", "/t2"])
    stop = threading.Event()
    player = BagPlayer(node, PlayOptions(bag=str(bag), rate=rate, delay_s=0.3,
                                         wait_subscribers_s=5.0), stop)
    result = {}
    th = threading.Thread(target=lambda: result.update(n=(player.wait_ready(), player.play())[1]))
    th.start()
    try:
        assert wait_for(lambda: len(got["/t1"]) == len(OFFSETS) and
                        len(got["/t2"]) == len(OFFSETS), 15.0 / rate, ex)
    finally:
        stop.set()
        th.join(10)
    assert result["n"] == 2 * len(OFFSETS) + 1
    assert [m.data for _, m in got["/t1"]] == [f"a{i}" for i in range(len(OFFSETS))]
    arrivals = np.array([t for t, _ in got["/t1"]])
    expected = np.diff(OFFSETS) / rate
    measured = np.diff(arrivals)
    print(f"rate {rate}: inter-arrival error ms {np.round((measured - expected) * 1e3, 1)}")
    np.testing.assert_allclose(measured, expected, atol=0.04)
    assert abs((arrivals[-1] - arrivals[0]) - OFFSETS[-1] / rate) < 0.04
    # /t2 comes 10 ms (bag time) after /t1 each time: interleaving order kept
    both = sorted([(t, m.data) for t, m in got["/t1"] + got["/t2"]])
    assert [d[0] for _, d in both] == list("ab" * len(OFFSETS))


def _play(bag: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "maem_ros.ros.player_node", str(bag),
                             "--wait-subscribers", "8", "--delay", "0.3", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ))


def test_loop_and_topic_filter(bag: Path, ros):
    node, ex = ros
    got = collect(node, ["/t1", "/t2"])
    with killed_on_exit(_play(bag, "--loop", "--topics", "/t1", "--rate", "4")) as proc:
        n = len(OFFSETS)
        assert wait_for(lambda: len(got["/t1"]) >= 2 * n + 1, 20.0, ex), proc.poll()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=15)
    assert proc.returncode == 0, out
    assert "interrupted" in out
    assert got["/t2"] == []
    data = [m.data for _, m in got["/t1"]]
    assert data[:2 * n + 1] == [f"a{i % n}" for i in range(2 * n + 1)]
    arrivals = np.array([t for t, _ in got["/t1"]])
    # loop restart: one average period (bag duration / (n-1)) after the last message, at rate 4
    gap = (OFFSETS[-1] / (n - 1)) / 4
    assert abs((arrivals[n] - arrivals[n - 1]) - gap) < 0.04
    np.testing.assert_allclose(np.diff(arrivals[n:2 * n]), np.diff(OFFSETS) / 4, atol=0.04)


def test_remap_start_offset_clock_and_latched(bag: Path, ros):
    node, ex = ros
    got = collect(node, ["/renamed", "/t2", "/clock"])
    scene = []
    node.create_subscription(String, bagio.SCENE_TOPIC, scene.append, LATCHED)
    with killed_on_exit(_play(bag, "--remap", "/t1:=/renamed", "--start", "0.2", "--clock",
                              "100")) as proc:
        wait_for(lambda: proc.poll() is not None, 30.0, ex)  # exits by itself (no --loop)
        wait_for(lambda: len(got["/t2"]) >= 5 and scene, 2.0, ex)
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, out
    later = [i for i, off in enumerate(OFFSETS) if off >= 0.2]
    assert [m.data for _, m in got["/renamed"]] == [f"a{i}" for i in later]
    assert [m.data for _, m in got["/t2"]] == [f"b{i}" for i in later]
    assert [m.data for m in scene] == ['{"seed": 3}']  # recorded before --start, still published
    clocks = [bagio.stamp_to_ns(m.clock) for _, m in got["/clock"]]
    assert len(clocks) > 10 and clocks == sorted(clocks)
    assert T0 + 0.2e9 <= clocks[0] and clocks[-1] <= T0 + int(OFFSETS[-1] * 1e9) + 10_000_000


def test_large_last_messages_are_delivered_before_exit(tmp_path: Path, ros):
    node, ex = ros
    path = tmp_path / "big"
    payloads = [chr(ord("a") + i) * 3_000_000 for i in range(3)]
    with bagio.BagWriter(path) as w:
        for i, text in enumerate(payloads):
            w.write("/big", bagio.string_msg(text), T0 + i * 1_000_000)
    got = collect(node, ["/big"], QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    with killed_on_exit(_play(path)) as proc:
        wait_for(lambda: proc.poll() is not None, 30.0, ex)
        wait_for(lambda: len(got["/big"]) == 3, 3.0, ex)
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, out
    assert [m.data[0] + str(len(m.data)) for _, m in got["/big"]] == ["a3000000", "b3000000",
                                                                       "c3000000"]


def test_bad_bag_and_topics_exit_with_message(tmp_path: Path, bag: Path):
    proc = subprocess.run([sys.executable, "-m", "maem_ros.ros.player_node", str(tmp_path / "none")],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "no such file or directory" in proc.stdout + proc.stderr
    proc = subprocess.run([sys.executable, "-m", "maem_ros.ros.player_node", str(bag), "--topics",
                           "/nothing", "--delay", "0"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "no topic to play" in proc.stdout + proc.stderr


def _image_bag(path: Path, frames: int, cameras=("c0", "c1")) -> Path:
    """Tiny CompressedImage frames 10 ms apart (bag time), every camera at the same log time."""
    from sensor_msgs.msg import CompressedImage

    from maem_ros.ros.wire import make_header
    with bagio.BagWriter(path) as w:
        for k in range(frames):
            t = T0 + k * 10_000_000
            for c in cameras:
                msg = CompressedImage(header=make_header(t, c), format="jpeg",
                                      data=bytes(range(256)) * 40)
                w.write(f"/{c}/image_raw/compressed", msg, t)
    return path


def test_lockstep_waits_for_the_consumer_and_images_are_reliable(tmp_path: Path, ros):
    """A slow consumer (0.4 s per frame, like a CPU frontend) that acknowledges each frame on
    /ack: maem-play --lockstep /ack --reliable-images sends the next frame only after the last
    one's ack, so every image arrives (reliable subscription) and none waits in a queue."""
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import Header

    from maem_ros.ros.qos import RELIABLE_IMAGE_QOS
    from maem_ros.ros.wire import ns_to_stamp
    node, ex = ros
    frames = 4
    bag = _image_bag(tmp_path / "bag", frames)
    ack = node.create_publisher(Header, "/ack", RELIABLE)
    arrivals: dict[int, list[float]] = {}
    acked: dict[int, float] = {}
    pending: list[tuple[float, int]] = []

    def on_image(msg) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        arrivals.setdefault(stamp, []).append(time.monotonic())
        if len(arrivals[stamp]) == 2:  # both cameras in: "process" for 0.4 s, then ack
            pending.append((time.monotonic() + 0.4, stamp))

    for c in ("c0", "c1"):
        node.create_subscription(CompressedImage, f"/{c}/image_raw/compressed", on_image,
                                 RELIABLE_IMAGE_QOS)

    def tick() -> bool:
        now = time.monotonic()
        for due, stamp in [p for p in pending if p[0] <= now]:
            pending.remove((due, stamp))
            ack.publish(Header(stamp=ns_to_stamp(stamp)))
            acked[stamp] = now
        return len(acked) == frames

    with killed_on_exit(_play(bag, "--lockstep", "/ack", "--lockstep-timeout", "20",
                              "--reliable-images", "--min-subscribers", "1")) as proc:
        assert wait_for(tick, 40.0, ex), (arrivals, acked)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "lockstep on ['/ack']: 0 frame(s) timed out" in out
    stamps = sorted(arrivals)
    assert len(stamps) == frames and all(len(arrivals[s]) == 2 for s in stamps)
    for prev, nxt in zip(stamps, stamps[1:]):  # frame k+1 only after frame k's ack
        assert min(arrivals[nxt]) >= acked[prev], (prev, nxt)


def test_lockstep_without_the_topic_is_a_clear_error(tmp_path: Path):
    bag = _image_bag(tmp_path / "bag", 1)
    done = subprocess.run([sys.executable, "-m", "maem_ros.ros.player_node", str(bag),
                           "--delay", "0", "--lockstep", "/nobody/acks"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--lockstep: ['/nobody/acks'] match no topic on the graph" in done.stderr + done.stdout
    with pytest.raises(SystemExit):
        parse_args([str(bag), "--lockstep", "/a", "--lockstep-timeout", "0"])
