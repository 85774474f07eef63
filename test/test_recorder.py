"""maem-record: every message it received is in the bag after SIGINT/SIGTERM; latched and late
topics; graph-discovered types; QoS adaptation."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from rclpy.duration import Duration
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import String

from maem_ros.ros.recorder_node import parse_args, wanted
from maem_ros import bagio

from helpers_ros import LATCHED, RELIABLE, killed_on_exit, ros_node, wait_for

# every test runs the recorder node
pytestmark = pytest.mark.ros

N = 60


@pytest.fixture
def ros():
    with ros_node("recorder_test") as (node, ex):
        yield node, ex


def test_parse_args_and_topic_selection():
    o = parse_args(["out", "--topics", "/a", "/b", "--all-maem"])
    assert o.topics == ["/a", "/b"] and o.all_maem
    assert wanted("/a", o) and wanted("/maem/poses", o) and not wanted("/c", o)
    assert wanted("/c", parse_args(["out", "--all"])) and not wanted("/rosout", parse_args(["out", "--all"]))
    with pytest.raises(SystemExit):
        parse_args(["out"])
    with pytest.raises(SystemExit):
        parse_args(["out", "--topics", "relative"])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_everything_received_is_in_the_bag(tmp_path: Path, ros, sig):
    node, ex = ros
    out = tmp_path / "rec"
    latched = node.create_publisher(String, "/maem/scene_test", LATCHED)
    latched.publish(String(data="latched before the recorder started"))
    pub = node.create_publisher(String, "/rec_a", RELIABLE)
    with killed_on_exit(subprocess.Popen(
            [sys.executable, "-m", "maem_ros.ros.recorder_node", str(out), "--topics", "/rec_a",
             "/rec_info", "--all-maem"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, env=dict(os.environ))) as proc:
        assert wait_for(lambda: pub.get_subscription_count() > 0, 20.0, ex), "recorder never subscribed"
        late = node.create_publisher(CameraInfo, "/rec_info", RELIABLE)  # appears after start
        assert wait_for(lambda: late.get_subscription_count() > 0, 10.0, ex), "late topic missed"
        for i in range(N):
            pub.publish(String(data=f"msg {i}"))
        info = CameraInfo(width=640, height=480, distortion_model="plumb_bob")
        info.header.frame_id = "cam"
        late.publish(info)
        # reliable: stop the recorder once it acknowledged everything
        assert pub.wait_for_all_acked(Duration(seconds=10)) and \
            late.wait_for_all_acked(Duration(seconds=10)), "recorder did not acknowledge"
        proc.send_signal(sig)
        text, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, text
    bag_info = bagio.bag_info(out)
    assert bag_info.topics == {"/rec_a": bagio.STRING, "/rec_info": bagio.CAMERA_INFO,
                               "/maem/scene_test": bagio.STRING}
    got = [m.decode().data for m in bagio.read_messages(out, ["/rec_a"])]
    assert got == [f"msg {i}" for i in range(N)]
    assert [m.decode().data for m in bagio.read_messages(out, ["/maem/scene_test"])] == [
        "latched before the recorder started"]
    assert bag_info.qos["/maem/scene_test"][0].durability == bagio.QosDurability.TRANSIENT_LOCAL
    (ci,) = [m.decode() for m in bagio.read_messages(out, ["/rec_info"])]
    assert (ci.width, ci.height, ci.header.frame_id) == (640, 480, "cam")
    assert f"wrote {N + 2} messages" in text
    assert text.rstrip().endswith("lost before the recorder took them: 0")


def test_existing_output_is_refused(tmp_path: Path):
    (tmp_path / "rec").mkdir()
    proc = subprocess.run([sys.executable, "-m", "maem_ros.ros.recorder_node", str(tmp_path / "rec"),
                           "--topics", "/x"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "exists already" in proc.stderr


def test_messages_lost_in_an_overflowing_queue_are_counted(tmp_path: Path, ros):
    """A recorder that falls behind (its executor stalled, as by a slow disk or a CPU stall)
    while a burst arrives keeps the newest RECORD_DEPTH messages of the burst; the rest are
    overwritten in the DDS keep-last history. Each is counted from the publisher's sequence
    numbers: lost = published - recorded, per topic in /diagnostics and in the last line."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from maem_ros.ros.recorder_node import RECORD_DEPTH, Recorder

    node, ex = ros
    burst = RECORD_DEPTH + 150
    out = tmp_path / "rec"
    rec_node = rclpy.create_node("maem_recorder", context=node.context)
    ex.add_node(rec_node)
    try:
        writer = bagio.BagWriter(out)
        rec = Recorder(rec_node, parse_args([str(out), "--topics", "/flood"]), writer)
        # the publisher keeps the whole burst until acknowledged: nothing is lost on its side
        pub = node.create_publisher(String, "/flood", QoSProfile(
            depth=2 * burst, reliability=ReliabilityPolicy.RELIABLE))

        def discovered() -> bool:
            rec.poll_graph()
            return "/flood" in rec.subs

        assert wait_for(discovered, 20.0, ex), "the recorder never saw /flood"
        assert wait_for(lambda: pub.get_subscription_count() > 0, 20.0, ex), "not matched"
        pub.publish(String(data="msg 0"))  # taken: the sequence numbers' start
        assert wait_for(lambda: rec.received == 1, 10.0, ex), "first message not received"
        for i in range(1, burst + 1):  # the recorder's executor is not spun meanwhile
            pub.publish(String(data=f"msg {i}"))
        assert pub.wait_for_all_acked(Duration(seconds=10)), "burst not delivered"
        assert wait_for(lambda: rec.received == 1 + RECORD_DEPTH, 10.0, ex), rec.received
        wait_for(lambda: False, 0.3, ex)  # nothing more comes
        writer.close()
        got = [m.decode().data for m in bagio.read_messages(out, ["/flood"])]
        published = burst + 1
        # the newest RECORD_DEPTH of the burst were kept, the older ones lost
        assert got == ["msg 0"] + [f"msg {i}" for i in range(burst - RECORD_DEPTH + 1, burst + 1)]
        assert rec.lost() == {"/flood": published - len(got)}
        assert published - len(got) == burst - RECORD_DEPTH > 0
        diag = rec.diag.snapshot()  # what the next /diagnostics message holds
        assert diag["dropped/dds_lost/flood"] == str(burst - RECORD_DEPTH)
        assert diag["received/flood"] == str(len(got)) == diag["frames_processed"]
        assert f"lost before the recorder took them: {burst - RECORD_DEPTH} " \
            f"(/flood: {burst - RECORD_DEPTH})" in rec.summary()
    finally:
        ex.remove_node(rec_node)
        rec_node.destroy_node()
