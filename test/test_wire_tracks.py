"""/maem/clusters with track ids: optional ``track`` / ``track_flags`` fields (temporal association)."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2

from helpers_scene import WIRE_RING, random_detections, ring_rig

from maem_ros.core.detections import Cluster
from maem_ros.core.tracking.temporal import FLAG_FEW_VIEWS, FLAG_TRACKED
from maem_ros.ros import wire


#: three random detections of 5 keypoints, no mesh (``camera``, ``seed`` per call)
dets = partial(random_detections, 3, 5, 0, stamp_ns=7, xy=(100.0, 600.0), score=0.9,
               kpts=(0.0, 700.0))


def roundtrip(msg: PointCloud2) -> PointCloud2:
    return deserialize_message(serialize_message(msg), PointCloud2)


CLUSTERS = [Cluster(np.array([[0, 2], [1, 0], [2, 1]]), np.full(3, np.nan)),
            Cluster(np.array([[0, 0], [2, 0]]), np.array([0.1, 0.2]))]


def test_track_ids_and_flags_roundtrip_per_cluster():
    rig = ring_rig(3, **WIRE_RING)
    frames = {c: dets(camera=c, seed=i) for i, c in enumerate(rig.names)}
    msg = wire.clusters_to_msg(9, "world", rig, frames, CLUSTERS, np.array([4, -1]),
                               np.array([FLAG_TRACKED | FLAG_FEW_VIEWS, 0]))
    cf = wire.msg_to_clusters(roundtrip(msg), "/maem/clusters", 3)
    assert cf.track.tolist() == [4, 4, 4, -1, -1]
    assert cf.cluster_tracks().tolist() == [4, -1]
    assert cf.track_flags.tolist() == [3, 3, 3, 0, 0]
    raw = np.frombuffer(bytes(msg.data), np.uint8)
    assert raw.size == msg.point_step * 5
    cam, _, _, present = cf.dense()  # the triangulation's cluster order = cluster_tracks order
    assert [cam[k][present[k]].tolist() for k in range(2)] == [[0, 1, 2], [0, 2]]


def test_clusters_without_tracks_keep_the_paper_layout():
    rig = ring_rig(3, **WIRE_RING)
    frames = {c: dets(camera=c, seed=i) for i, c in enumerate(rig.names)}
    msg = wire.clusters_to_msg(9, "world", rig, frames, CLUSTERS)
    assert [f.name for f in msg.fields] == ["cluster", "camera", "detection", "score", "cost",
                                            "kpts2d"]
    cf = wire.msg_to_clusters(roundtrip(msg), "/maem/clusters", 3)
    assert cf.track is None and cf.track_flags is None and cf.cluster_tracks() is None
    empty = wire.msg_to_clusters(wire.clusters_to_msg(9, "world", rig, frames, [], np.zeros(0)),
                                 "/maem/clusters", 3)
    assert empty.track.size == 0 and empty.cluster_tracks().size == 0


def test_bad_track_fields_are_wire_errors():
    rig = ring_rig(3, **WIRE_RING)
    frames = {c: dets(camera=c, seed=i) for i, c in enumerate(rig.names)}
    msg = wire.clusters_to_msg(9, "world", rig, frames, CLUSTERS, np.array([4, 5]))
    rec = np.frombuffer(bytearray(bytes(msg.data)), np.uint8).copy()
    off = next(f.offset for f in msg.fields if f.name == "track")
    rec[msg.point_step + off] ^= 1  # the second member of cluster 0 claims another track
    msg.data = rec.tobytes()
    with pytest.raises(wire.WireError, match="different track ids") as e:
        wire.msg_to_clusters(msg, "/maem/clusters", 3)
    assert e.value.reason == "bad_track"
    msg = wire.clusters_to_msg(9, "world", rig, frames, CLUSTERS, np.array([4, 5]))
    msg.fields = [f for f in msg.fields if f.name != "track_flags"]
    with pytest.raises(wire.WireError, match="track_flags: missing field"):
        wire.msg_to_clusters(msg, "/maem/clusters", 3)
