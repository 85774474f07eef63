"""The wire (maem_ros/wire, its ROS adapters ros/wire): PointCloud2 / MarkerArray / Image layouts,
round trips, validation, garbage input."""
from __future__ import annotations

import array
import time
from dataclasses import dataclass
from functools import partial

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from visualization_msgs.msg import Marker

from helpers_scene import WIRE_RING, random_detections, ring_rig

from maem_ros.core.detections import FrameDetections
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.ros import wire
from maem_ros import bagio

TOPIC = "/camera_0/detections"
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


#: the wire tests' random detections: full-HD-ish numbers, keypoints and vertices a little
#: outside the image, a realistic stamp
make_dets = partial(random_detections, camera="camera_0", stamp_ns=1_700_000_000_123_456_789,
                    box=(0.0, 300.0), kpts=(-50.0, 1500.0), verts=(-50.0, 1500.0))


def assert_dets_equal(a: FrameDetections, b: FrameDetections) -> None:
    assert (a.camera, a.stamp_ns, a.n, a.num_joints, a.num_vertices) == \
        (b.camera, b.stamp_ns, b.n, b.num_joints, b.num_vertices)
    for name in ("bboxes", "scores", "kpts2d", "kpts3d", "verts2d"):
        np.testing.assert_array_equal(getattr(a, name).astype(np.float32),
                                      getattr(b, name).astype(np.float32), err_msg=name)


def roundtrip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


# ---------------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------------
@FAST
@given(n=st.integers(0, 6), j=st.integers(1, 20), v=st.integers(0, 40), seed=st.integers(0, 2**16),
       stamp=st.integers(0, wire.MAX_STAMP_NS))
def test_detections_roundtrip(n, j, v, seed, stamp):
    dets = make_dets(n, j, v, seed, stamp_ns=stamp)
    msg = wire.detections_to_msg(dets)
    assert msg.header.frame_id == "camera_0" and msg.width == n and msg.height == 1
    assert {f.name: f.count for f in msg.fields} == {"bbox": 4, "score": 1, "kpts2d": 2 * j,
                                                     "kpts3d": 3 * j, "verts2d": 2 * v}
    assert len(msg.data) == msg.row_step == n * msg.point_step
    back = wire.msg_to_detections(roundtrip(msg), TOPIC, ["camera_0"], expected_camera="camera_0")
    assert_dets_equal(dets, back)


def test_detections_decode_is_zero_copy_and_fast():
    dets = make_dets(12, 70, 18439)
    t0 = time.perf_counter()
    for _ in range(5):
        msg = wire.detections_to_msg(dets)
    enc_ms = (time.perf_counter() - t0) / 5 * 1e3
    msg = roundtrip(msg)
    t0 = time.perf_counter()
    for _ in range(5):
        back = wire.msg_to_detections(msg, TOPIC)
    dec_ms = (time.perf_counter() - t0) / 5 * 1e3
    assert np.shares_memory(back.verts2d, np.frombuffer(msg.data, np.uint8))
    assert_dets_equal(dets, back)
    assert len(msg.data) == 12 * 4 * (5 + 5 * 70 + 2 * 18439)
    # generous bounds for a loaded 2-core machine; typically ~0.5 ms and ~0.2 ms
    assert enc_ms < 100 and dec_ms < 50, (enc_ms, dec_ms)


@dataclass
class FakeCluster:
    members: np.ndarray
    costs: np.ndarray


@FAST
@given(sizes=st.lists(st.integers(1, 3), min_size=0, max_size=4), j=st.integers(1, 15),
       seed=st.integers(0, 1000))
def test_clusters_roundtrip(sizes, j, seed):
    rig = ring_rig(3, **WIRE_RING)
    rng = np.random.default_rng(seed)
    frames = {c: make_dets(4, j, 5, seed + i, camera=c) for i, c in enumerate(rig.names)}
    clusters, used = [], set()
    for k, size in enumerate(sizes):
        members = []
        for c in rng.permutation(3)[:size]:
            d = int(rng.integers(4))
            if (c, d) not in used:
                used.add((c, d))
                members.append((int(c), d))
        if members:
            clusters.append(FakeCluster(np.array(members), rng.uniform(0, 0.3, len(members))))
    msg = wire.clusters_to_msg(123, "world", rig, frames, clusters)
    cf = wire.msg_to_clusters(roundtrip(msg), "/maem/clusters", len(rig))
    assert cf.stamp_ns == 123 and cf.frame_id == "world" and cf.num_joints == j
    rows = [(k, c, d) for k, cl in enumerate(clusters) for c, d in cl.members]
    assert list(zip(cf.cluster, cf.camera, cf.detection)) == rows
    for i, (k, c, d) in enumerate(rows):
        f = frames[rig.names[c]]
        np.testing.assert_allclose(cf.kpts2d[i], f.kpts2d[d], rtol=1e-6, atol=1e-3)
        assert cf.score[i] == pytest.approx(f.scores[d], abs=1e-6)


def test_clusters_dense_members_equal_the_sent_rows():
    rig = ring_rig(3, **WIRE_RING)
    frames = {c: make_dets(3, 4, 2, i, camera=c) for i, c in enumerate(rig.names)}
    clusters = [FakeCluster(np.array([[0, 2], [2, 1]]), np.array([0.1, 0.2])),
                FakeCluster(np.array([[1, 0], [2, 0], [0, 0]]), np.array([0.1, 0.2, np.nan]))]
    cf = wire.msg_to_clusters(wire.clusters_to_msg(5, "world", rig, frames, clusters), "t", 3)
    cam, uv, score, present = cf.dense()
    assert cam.shape == (2, 3) and present.tolist() == [[True, True, False], [True, True, True]]
    for k, orig in enumerate(clusters):
        for m, (c, d) in enumerate(orig.members):
            assert cam[k, m] == c
            np.testing.assert_allclose(uv[k, m], frames[rig.names[c]].kpts2d[d], atol=1e-3)
            assert score[k, m] == pytest.approx(frames[rig.names[c]].scores[d], abs=1e-6)
    assert np.isnan(uv[0, 2]).all()


@FAST
@given(p=st.integers(0, 5), j=st.integers(1, 20), seed=st.integers(0, 1000))
def test_poses_roundtrip_keeps_nan_and_untracked(p, j, seed):
    rng = np.random.default_rng(seed)
    joints = rng.normal(0, 5, (p, j, 3))
    joints[rng.uniform(size=(p, j)) < 0.2] = np.nan
    ids = rng.integers(-1, 50, p)
    views = rng.integers(2, 7, p)
    scores = rng.uniform(0, 1, p)
    pf = wire.msg_to_poses(roundtrip(wire.poses_to_msg(9, "world", ids, joints, views, scores)),
                           "/maem/poses")
    np.testing.assert_array_equal(pf.ids, np.where(ids < 0, wire.UNTRACKED_ID, ids))
    np.testing.assert_array_equal(np.isnan(pf.joints), np.isnan(joints))
    np.testing.assert_allclose(pf.joints, joints, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(pf.views, views)
    np.testing.assert_allclose(pf.scores, scores, rtol=1e-6)
    assert pf.joints.shape == (p, j, 3)


# ---------------------------------------------------------------------------------------------
# validation: one WireError naming topic, field, problem
# ---------------------------------------------------------------------------------------------
def _mutate(msg: PointCloud2, name: str, **kw) -> PointCloud2:
    msg.fields = [PointField(name=kw.get("rename", f.name), offset=f.offset,
                             datatype=kw.get("datatype", f.datatype), count=kw.get("count", f.count))
                  if f.name == name else f for f in msg.fields]
    return msg


def _with_value(field: str, index, value) -> PointCloud2:
    dets = make_dets(3, 5, 4)
    getattr(dets, field)[index] = value
    return wire.detections_to_msg(dets)


BAD = {
    "missing_field": (lambda m: setattr(m, "fields", [f for f in m.fields if f.name != "kpts3d"])
                      or m, "kpts3d", "missing_field"),
    "unknown_field": (lambda m: _mutate(m, "score", rename="confidence"), "confidence",
                      "unknown_field"),
    "bad_count": (lambda m: _mutate(m, "kpts3d", count=14), "kpts3d", "bad_count"),
    "odd_kpts2d": (lambda m: _mutate(m, "kpts2d", count=9), "kpts2d", "bad_count"),
    "bbox_count": (lambda m: _mutate(m, "bbox", count=3), "bbox", "bad_count"),
    "bad_datatype": (lambda m: _mutate(m, "score", datatype=PointField.FLOAT64), "score",
                     "bad_datatype"),
    "short_data": (lambda m: setattr(m, "data", m.data[:-4]) or m, "data", "bad_size"),
    "zero_size_data": (lambda m: setattr(m, "data", array.array("B")) or m, "data", "bad_size"),
    "row_step": (lambda m: setattr(m, "row_step", m.row_step + 1) or m, "row_step", "bad_size"),
    "point_step": (lambda m: setattr(m, "point_step", m.point_step - 4) or m, "verts2d",
                   "bad_layout"),
    "unknown_camera": (lambda m: setattr(m.header, "frame_id", "camera_9") or m,
                       "header.frame_id", "unknown_camera"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_detections_decoder_rejects(case):
    mutate, field, reason = BAD[case]
    msg = roundtrip(mutate(wire.detections_to_msg(make_dets(3, 5, 4))))
    with pytest.raises(wire.WireError) as ei:
        wire.msg_to_detections(msg, TOPIC, ["camera_0", "camera_1"])
    assert ei.value.reason == reason and ei.value.field == field
    assert str(ei.value).startswith(f"{TOPIC}: {field}: ")


@pytest.mark.parametrize("field,index,value,name,reason", [
    ("kpts2d", (1, 2, 0), np.inf, "kpts2d", "nonfinite"),  # NaN = keypoint not seen
    ("verts2d", (2, 3, 1), np.inf, "verts2d", "nonfinite"),
    ("kpts3d", (0, 0, 2), -np.inf, "kpts3d", "nonfinite"),
    ("bboxes", (1, 2), -5.0, "bbox", "inverted_bbox"),
    ("scores", 2, 1.5, "score", "bad_score"),
])
def test_detections_decoder_rejects_values(field, index, value, name, reason):
    dets = make_dets(3, 5, 4)
    dets.bboxes[1] = [10, 10, 20, 20]
    getattr(dets, field)[index] = value
    with pytest.raises(wire.WireError) as ei:
        wire.msg_to_detections(wire.detections_to_msg(dets), TOPIC)
    assert (ei.value.field, ei.value.reason) == (name, reason)
    assert "detection" in ei.value.problem


def test_detections_decoder_rejects_an_inf_vertex_of_a_large_mesh_naming_the_detection():
    """The decoder's finiteness check of verts2d (NaN = missing is allowed, inf never is) on a
    mesh the size of the pair gates' screening subsets: the detection is named."""
    dets = make_dets(3, 5, 2000)
    dets.verts2d[1, 7] = np.nan
    got = wire.msg_to_detections(wire.detections_to_msg(dets), TOPIC)
    assert np.isnan(got.verts2d[1, 7]).all()
    dets.verts2d[2, 1000, 1] = np.inf
    with pytest.raises(wire.WireError) as ei:
        wire.msg_to_detections(wire.detections_to_msg(dets), TOPIC)
    assert (ei.value.field, ei.value.reason, ei.value.problem) == \
        ("verts2d", "nonfinite", "inf in detection 2")


def test_stamps_outside_ros_time_are_rejected():
    assert wire.stamp_to_ns(wire.ns_to_stamp(wire.MAX_STAMP_NS)) == wire.MAX_STAMP_NS
    for bad in (-1, wire.MAX_STAMP_NS + 1):
        with pytest.raises(ValueError, match="stamp"):
            wire.detections_to_msg(make_dets(1, 2, 0, stamp_ns=bad))


@pytest.mark.parametrize("sec,nanosec", [(-3, 0), (1, 1_000_000_000), (2**31 - 1, 4_000_000_000)])
def test_received_invalid_stamps_are_wire_errors(sec, nanosec):
    msgs = {
        wire.msg_to_detections: wire.detections_to_msg(make_dets(1, 2, 0)),
        wire.msg_to_poses: wire.poses_to_msg(9, "world", np.array([1]), np.zeros((1, 2, 3)),
                                             np.array([2]), np.array([0.9])),
    }
    for decode, msg in msgs.items():
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        with pytest.raises(wire.WireError) as ei:
            decode(msg, "/t")
        assert (ei.value.field, ei.value.reason) == ("header.stamp", "bad_stamp")


def test_cdr_header_stamp():
    stamp = 1_700_000_000_123_456_789
    data = bagio.serialize(wire.compressed_image_msg(b"\xff\xd8", "jpeg", stamp, "camera_0"))
    assert wire.cdr_header_stamp_ns(data) == stamp
    with pytest.raises(ValueError, match="too short"):
        wire.cdr_header_stamp_ns(b"\x00\x01\x00\x00")


def test_camera_mismatch_and_empty_frame():
    msg = wire.detections_to_msg(FrameDetections.empty("camera_1", 42, 70, 18439))
    with pytest.raises(wire.WireError, match="camera_mismatch|on the topic of camera") as ei:
        wire.msg_to_detections(msg, TOPIC, ["camera_0", "camera_1"], expected_camera="camera_0")
    assert ei.value.reason == "camera_mismatch"
    empty = wire.msg_to_detections(roundtrip(msg), "/camera_1/detections", ["camera_1"])
    assert (empty.n, empty.num_joints, empty.num_vertices, empty.stamp_ns) == (0, 70, 18439, 42)


def test_big_endian_cloud_decodes():
    dets = make_dets(2, 3, 2)
    msg = wire.detections_to_msg(dets)
    raw = np.frombuffer(msg.data, np.float32).astype(">f4")
    msg.data = array.array("B", raw.tobytes())
    msg.is_bigendian = True
    assert_dets_equal(dets, wire.msg_to_detections(msg, TOPIC))


def test_cluster_and_pose_decoders_reject():
    rig = ring_rig(3, **WIRE_RING)
    frames = {c: make_dets(2, 4, 1, i, camera=c) for i, c in enumerate(rig.names)}
    msg = wire.clusters_to_msg(1, "world", rig, frames,
                               [FakeCluster(np.array([[0, 0], [2, 1]]), np.zeros(2))])
    with pytest.raises(wire.WireError) as ei:
        wire.msg_to_clusters(msg, "/maem/clusters", 2)
    assert (ei.value.field, ei.value.reason) == ("camera", "unknown_camera")
    dup = wire.clusters_to_msg(1, "world", rig, frames,
                               [FakeCluster(np.array([[0, 0], [2, 1]]), np.zeros(2)),
                                FakeCluster(np.array([[0, 0], [1, 1]]), np.zeros(2))])
    with pytest.raises(wire.WireError, match="appears twice"):
        wire.msg_to_clusters(dup, "/maem/clusters", 3)
    poses = wire.poses_to_msg(1, "world", [1], np.full((1, 2, 3), np.inf), [2], [0.5])
    with pytest.raises(wire.WireError) as ei:
        wire.msg_to_poses(poses, "/maem/poses")
    assert (ei.value.field, ei.value.reason) == ("joints", "nonfinite")


# ---------------------------------------------------------------------------------------------
# garbage never raises anything but WireError
# ---------------------------------------------------------------------------------------------
NAMES = ["bbox", "score", "kpts2d", "kpts3d", "verts2d", "cluster", "camera", "detection", "cost",
         "id", "joints", "views", "x", ""]

field_st = st.builds(lambda name, off, dt, count: PointField(name=name, offset=off, datatype=dt,
                                                             count=count),
                     st.sampled_from(NAMES), st.integers(0, 64), st.integers(0, 9),
                     st.integers(0, 12))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fields=st.lists(field_st, max_size=8), width=st.integers(0, 4), height=st.integers(0, 2),
       point_step=st.integers(0, 80), row_step=st.integers(0, 400), big=st.booleans(),
       data=st.binary(max_size=400), frame_id=st.sampled_from(["camera_0", "x", ""]))
@pytest.mark.slow
def test_garbage_clouds_raise_only_wire_errors(fields, width, height, point_step, row_step, big,
                                               data, frame_id):
    msg = PointCloud2(height=height, width=width, fields=fields, is_bigendian=big,
                      point_step=point_step, row_step=row_step, data=array.array("B", data))
    msg.header.frame_id = frame_id
    for decode in (lambda m: wire.msg_to_detections(m, TOPIC, ["camera_0"]),
                   lambda m: wire.msg_to_clusters(m, "/maem/clusters", 3),
                   lambda m: wire.msg_to_poses(m, "/maem/poses")):
        try:
            decode(msg)
        except wire.WireError as e:
            assert e.topic and e.field and e.problem and e.reason


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
       cut=st.integers(0, 8), count_delta=st.integers(-3, 3), which=st.integers(0, 4))
def test_corrupted_valid_clouds_decode_or_raise_wire_errors(flips, cut, count_delta, which):
    msg = wire.detections_to_msg(make_dets(3, 4, 3))
    data = bytearray(msg.data)
    for pos, val in flips:
        data[pos % len(data)] = val
    msg.data = array.array("B", bytes(data[:len(data) - cut]))
    f = msg.fields[which]
    f.count = max(0, f.count + count_delta)
    try:
        dets = wire.msg_to_detections(msg, TOPIC, ["camera_0"])
    except wire.WireError:
        return
    dets.validate(["camera_0"])  # anything accepted is a valid FrameDetections


# ---------------------------------------------------------------------------------------------
# markers and images
# ---------------------------------------------------------------------------------------------
def test_skeleton_markers_well_formed():
    rng = np.random.default_rng(1)
    joints = rng.normal(0, 1, (3, 13, 3)) + [0, 0, 1]
    joints[0, 5] = np.nan  # left_wrist-ish joint missing -> its bones skipped
    joints[2] = np.nan  # nothing finite -> no markers
    arr = wire.skeleton_markers(10**9 + 5, "world", [7, -1, 13], joints, SPORTCENTER_13.bones, 0.5)
    assert len(arr.markers) == 1 + 3  # tentative id -1 and all-NaN person 13 are skipped
    arr = wire.skeleton_markers(10**9 + 5, "world", [7, 12, 13], joints, SPORTCENTER_13.bones, 0.5)
    # the previous frame's markers are deleted first (DELETEALL), then this frame's added
    clear = arr.markers[0]
    assert (clear.action, clear.ns, clear.header.stamp.sec) == (Marker.DELETEALL,
                                                                 wire.NS_DELETE_ALL, 1)
    empty = wire.skeleton_markers(10**9, "world", [], np.zeros((0, 13, 3)), SPORTCENTER_13.bones)
    assert [m.action for m in empty.markers] == [Marker.DELETEALL]
    arr.markers = arr.markers[1:]
    assert len(arr.markers) == 6
    by = {(m.ns, m.id): m for m in arr.markers}
    assert set(by) == {(ns, i) for ns in (wire.NS_JOINTS, wire.NS_BONES, wire.NS_LABELS)
                       for i in (7, 12)}
    for m in arr.markers:
        assert m.header.frame_id == "world" and m.header.stamp.sec == 1 and m.header.stamp.nanosec == 5
        assert m.action == Marker.ADD and m.lifetime.nanosec == 500_000_000 and m.lifetime.sec == 0
        assert m.color.a == 1.0 and m.pose.orientation.w == 1.0
    j7 = by[(wire.NS_JOINTS, 7)]
    assert j7.type == Marker.SPHERE_LIST and len(j7.points) == 12 and j7.scale.x > 0
    b7 = by[(wire.NS_BONES, 7)]
    assert b7.type == Marker.LINE_LIST and len(b7.points) % 2 == 0 and b7.scale.x > 0
    n_ok = sum(1 for a, b in SPORTCENTER_13.bones if a != 5 and b != 5)
    assert len(b7.points) == 2 * n_ok < 2 * len(SPORTCENTER_13.bones)
    for p in b7.points:
        assert np.isfinite([p.x, p.y, p.z]).all()
    t12 = by[(wire.NS_LABELS, 12)]
    assert t12.type == Marker.TEXT_VIEW_FACING and t12.text == "12"
    assert t12.pose.position.z == pytest.approx(np.nanmax(joints[1, :, 2]) + 0.3)
    assert by[(wire.NS_JOINTS, 7)].color != by[(wire.NS_JOINTS, 12)].color


def test_skeleton_marker_points_are_the_joints_and_bone_ends():
    """Joint lists hold each shown person's finite joints in order, bone lists both ends of
    every bone with two finite ends, whoever is skipped before them in the frame."""
    rng = np.random.default_rng(2)
    joints = rng.normal(0, 1, (4, 13, 3))
    joints[rng.random((4, 13)) < 0.3] = np.nan
    ids = [-1, 3, 9, 4]  # a tentative person first: not shown, its joints not in any list
    arr = wire.skeleton_markers(0, "world", ids, joints, SPORTCENTER_13.bones, 0.5)
    by = {(m.ns, m.id): m for m in arr.markers[1:]}
    xyz = lambda m: np.array([[p.x, p.y, p.z] for p in m.points]).reshape(-1, 3)  # noqa: E731
    for p, pid in enumerate(ids[1:], start=1):
        finite = np.isfinite(joints[p]).all(-1)
        np.testing.assert_array_equal(xyz(by[(wire.NS_JOINTS, pid)]), joints[p][finite])
        ok = [(a, b) for a, b in SPORTCENTER_13.bones if finite[a] and finite[b]]
        want = joints[p][np.array(ok, dtype=int).reshape(-1)].reshape(-1, 3)
        np.testing.assert_array_equal(xyz(by[(wire.NS_BONES, pid)]), want)


def test_image_helpers():
    import cv2
    img = np.random.default_rng(0).integers(0, 255, (6, 5, 3), dtype=np.uint8)
    msg = roundtrip(wire.bgr_to_image(img, 77, "camera_0"))
    np.testing.assert_array_equal(wire.image_to_bgr(msg, "/camera_0/image_raw"), img)
    rgb = Image(height=6, width=5, encoding="rgb8", step=16,
                data=np.pad(img[:, :, ::-1], ((0, 0), (0, 1), (0, 0)))[:, :, :].reshape(6, -1)[:, :16]
                .tobytes())
    np.testing.assert_array_equal(wire.image_to_bgr(rgb, "t"), img)
    ok, jpg = cv2.imencode(".png", img)
    comp = CompressedImage(format="png", data=jpg.tobytes())
    np.testing.assert_array_equal(wire.compressed_to_bgr(comp, "t"), img)
    for bad, reason in ((Image(height=2, width=2, encoding="16UC1", step=4, data=bytes(8)),
                         "bad_encoding"),
                        (Image(height=2, width=2, encoding="bgr8", step=6, data=bytes(11)), "bad_size")):
        with pytest.raises(wire.WireError) as ei:
            wire.image_to_bgr(bad, "/camera_0/image_raw")
        assert ei.value.reason == reason
    with pytest.raises(wire.WireError) as ei:
        wire.compressed_to_bgr(CompressedImage(format="jpeg", data=b"notajpeg"), "t")
    assert ei.value.reason == "bad_encoding"
