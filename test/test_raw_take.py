"""ros.raw_take: serialized samples taken by librcl into arrays (no rclpy bytes copy), by
take_pending and by the executor the nodes spin, with rclpy's message info."""
from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest
from rclpy.duration import Duration
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2

from maem_ros.ros import raw_take, wire
from maem_ros.ros.diagnostics import Diagnostics
from maem_ros.ros.intake import subscribe_counted, take_pending

from helpers_ros import RELIABLE, ros_node, wait_for


def _messages(scene) -> list[bytes]:
    """Serialized detections of every size the node sees: a full frame, an empty one, q4."""
    dets = scene.detections("camera_0", 1)
    return [bytes(serialize_message(wire.detections_to_msg(d, layout)))
            for d, layout in ((dets, "f32"), (dets.select(np.arange(0)), "f32"), (dets, "q4"))]


def _subscription(node, got: list, into_array: bool = True):
    diag = Diagnostics(node)
    sub = subscribe_counted(node, diag, PointCloud2, "/raw_take", lambda m, i: got.append((m, i)),
                            RELIABLE, raw=True, with_info=True, into_array=into_array)
    pub = node.create_publisher(PointCloud2, "/raw_take", RELIABLE)
    assert wait_for(lambda: pub.get_subscription_count() == 1, 10.0)
    return sub, pub


def test_samples_come_as_arrays_of_their_serialized_bytes_with_rclpy_info(graph, scene):
    """Through the nodes' executor: each sample is a uint8 array equal to the bytes published,
    its info has rclpy's keys, sequence numbers count up by one and times are in order; the
    samples decode as the bytes do."""
    assert raw_take._rcl() is not None  # the pinned wheels' librcl is loaded by rclpy
    got: list = []
    sub, pub = _subscription(graph.client("raw_take_test"), got)
    sent = _messages(scene) * 2
    for data in sent:
        pub.publish(data)
    assert wait_for(lambda: len(got) == len(sent), 10.0, graph)
    for (data, info), want in zip(got, sent):
        assert isinstance(data, np.ndarray) and data.dtype == np.uint8
        assert data.tobytes() == want
        assert set(info) == {"source_timestamp", "received_timestamp",
                             "publication_sequence_number", "reception_sequence_number"}
        assert 0 < info["source_timestamp"] <= info["received_timestamp"]
    seqs = [info["publication_sequence_number"] for _, info in got]
    assert seqs == list(range(seqs[0], seqs[0] + len(sent)))
    fast = wire.msg_to_detections(wire.cdr_to_cloud(got[0][0], "/t"), "/t")
    ref = wire.msg_to_detections(wire.cdr_to_cloud(sent[0], "/t"), "/t")
    np.testing.assert_array_equal(fast.verts2d, ref.verts2d)
    assert np.shares_memory(fast.verts2d, got[0][0])  # decoded in place


@pytest.mark.ros
def test_take_pending_takes_into_arrays_and_the_buffer_goes_with_its_last_view(scene):
    """take_pending on a marked subscription: arrays (rclpy's take gives bytes for the same
    topic unmarked); the malloc'd buffer is owned by the array and freed once nothing views it;
    nothing waiting: None."""
    with ros_node("raw_take_test") as (node, _):  # nothing spins it: taken by hand only
        got: list = []
        sub, pub = _subscription(node, got)
        sent = _messages(scene)
        for data in sent:
            pub.publish(data)
        assert pub.wait_for_all_acked(Duration(seconds=10))
        assert take_pending(sub, limit=1) == 1
        setattr(sub, raw_take.ARRAY_TAKE, False)
        assert take_pending(sub, limit=1) == 1
        setattr(sub, raw_take.ARRAY_TAKE, True)
        assert take_pending(sub) == len(sent) - 2
        assert [type(m) for m, _ in got] == [np.ndarray, bytes, np.ndarray]
        assert [bytes(m) for m, _ in got] == sent
        with sub.handle:
            assert raw_take.take_into_array(sub) is None
        view = got[0][0][100:]
        owner = weakref.ref(got[0][0].base)
        assert isinstance(owner(), raw_take._MallocBuffer)
        got.clear()
        gc.collect()
        assert owner() is not None  # the slice still views the buffer
        del view
        gc.collect()
        assert owner() is None
