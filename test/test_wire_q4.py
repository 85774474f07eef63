"""Compact detections layout (verts2d_q4 / kpts2d_q4), announced vertex subsets, and what they do
to the association: same clusters as float32, subsets honoured, validation done once."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointField

from maem_ros.core.association.gates import epipolar
from maem_ros.core.association.pipeline import AssociationParams, associate
from maem_ros.core.detections import FrameDetections
from maem_ros.core.synthetic import body_template, make_frame
from maem_ros.params import load_node_params
from maem_ros.ros import wire
from maem_ros.sim.rigs import load_rig

from helpers_scene import random_detections

TOPIC = "/camera_0/detections"
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def roundtrip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


#: random detections across a 4000 px image (the q4 range), camera_0
make_dets = partial(random_detections, camera="camera_0", stamp_ns=5, kpts=(0.0, 4000.0),
                    verts=(0.0, 4000.0))


@FAST
@given(n=st.integers(0, 5), j=st.integers(1, 12), v=st.integers(0, 50), seed=st.integers(0, 2**16))
def test_q4_round_trip_is_exact_to_a_32nd_of_a_pixel(n, j, v, seed):
    dets = make_dets(n, j, v, seed, verts=(-30.0, 4200.0))  # some vertices outside the q4 range
    msg = roundtrip(wire.detections_to_msg(dets, vertices="q4", keypoints="q4"))
    names = {f.name: (f.datatype, f.count) for f in msg.fields}
    assert names["verts2d_q4"] == (PointField.UINT16, 2 * v) and "verts2d" not in names
    assert names["kpts2d_q4"] == (PointField.UINT16, 2 * j) and "kpts2d" not in names
    back = wire.msg_to_detections(msg, TOPIC)
    assert back.verts2d.dtype == np.float32 and back.verts2d.shape == (n, v, 2)
    # codes count from each detection's origin, the floor of its smallest coordinates
    origin = np.floor(dets.verts2d.min(axis=1, keepdims=True)) if v else 0.0
    rel = dets.verts2d - origin
    inside = (rel > -1 / 32) & (rel < 65534 / 16 + 1 / 32)
    # a vertex is missing as a whole when one of its coordinates is outside
    inside_pt = np.repeat(np.all(inside, axis=-1, keepdims=True), 2, axis=-1)
    assert np.all(np.abs(back.verts2d[inside_pt] - dets.verts2d[inside_pt]) <= 1 / 32 + 1e-4)
    assert np.all(np.isnan(back.verts2d[~inside]))  # outside the q4 range: missing
    assert np.all(np.abs(back.kpts2d - dets.kpts2d) <= 1 / 32 + 1e-9)
    # q4 halves the vertex and keypoint bytes (+ 8 bytes of origin per detection)
    f32 = wire.detections_to_msg(dets)
    assert len(msg.data) == len(f32.data) - n * 4 * (v + j) + n * 8


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 5), pairs=st.integers(0, 40), seed=st.integers(0, 2**16),
       read_only=st.booleans())
def test_q4_kernel_decodes_exactly_as_numpy(n, pairs, seed, read_only):
    """The numba decoder (float32, rows contiguous as in a received message) gives the same
    bits as the numpy path (float64, cast: every q4 value is exact in float32)."""
    from maem_ros.core.jit import have_numba
    from maem_ros.wire.q4_kernel import decode_pairs
    rng = np.random.default_rng(seed)
    record = np.zeros(n, np.dtype([("bbox", np.float32, 4), ("code", np.uint16, 2 * pairs)]))
    record["code"] = rng.integers(0, wire.Q4_MISSING + 1, (n, 2 * pairs))
    record["code"][rng.random((n, 2 * pairs)) < 0.1] = wire.Q4_MISSING
    if read_only:  # the fields of a received message are views of its bytes
        record = np.frombuffer(record.tobytes(), record.dtype)
    code = record["code"]
    origin = np.floor(rng.uniform(-2000, 2000, (n, 2))).astype(np.float32)
    fast = wire.decode_q4(code, origin=origin)
    reference = wire.decode_q4(code, np.float64, origin=origin).astype(np.float32)
    assert fast.dtype == np.float32 and fast.shape == code.shape
    np.testing.assert_array_equal(fast, reference)  # NaN where missing, in both
    assert np.isnan(fast).sum() == (code == wire.Q4_MISSING).sum()
    if have_numba():
        assert decode_pairs(code, origin) is not None  # the kernel ran, not the fallback


def test_q4_codes_and_missing_values():
    # 65534 / 16 = 4095.875 px is the largest value; 65535 marks a missing one
    px = np.array([0.0, 1 / 32 - 1e-6, 100.03125, 4095.875, 4095.9375, -0.02, -5.0, np.nan, 1e9])
    code = wire.encode_q4(px)
    assert code.tolist() == [0, 0, 1600, 65534, 65535, 0, 65535, 65535, 65535]
    back = wire.decode_q4(code)
    assert back[2] == np.float32(100.0) and back[3] == np.float32(4095.875)
    assert np.isnan(back[4]) and np.all(np.isnan(back[6:])) and back[5] == 0.0


def test_q4_carries_people_at_negative_rectified_coordinates():
    """Wide distorted cameras put whole people at u < 0 in the rectified image: the origin keeps
    them (a fixed 0 origin would mark every vertex missing)."""
    dets = make_dets(2, 3, 50, verts=(-900.0, -20.0))
    back = wire.msg_to_detections(wire.detections_to_msg(dets, vertices="q4"), TOPIC)
    assert np.all(np.abs(back.verts2d - dets.verts2d) <= 1 / 32 + 1e-4)
    assert np.all(wire.encode_q4(dets.verts2d) == wire.Q4_MISSING)  # what origin 0 would send
    msg = wire.detections_to_msg(dets, vertices="q4")
    msg.fields = [f for f in msg.fields if f.name != wire.ORIGIN_FIELD]  # optional field: the
    np.testing.assert_allclose(  # codes then count from 0 0 (the plain q4 layout)
        wire.msg_to_detections(msg, TOPIC).verts2d,
        (dets.verts2d - np.floor(dets.verts2d.min(axis=1, keepdims=True))), atol=1 / 32 + 1e-4)


def _q4_message(n=2, j=3, v=4):
    return wire.detections_to_msg(make_dets(n, j, v, verts=(0.0, 1000.0)), vertices="q4", keypoints="q4")


def test_q4_out_of_range_keypoints_go_f32_and_unseen_ones_are_nan():
    dets = make_dets(2, 3, 4)
    dets.kpts2d[1, 0, 0] = -3.0  # q4 cannot carry it: this message sends f32 keypoints
    back = wire.msg_to_detections(wire.detections_to_msg(dets, keypoints="q4"), TOPIC)
    np.testing.assert_array_equal(back.kpts2d, dets.kpts2d.astype(np.float32))
    dets = make_dets(2, 3, 4)
    dets.kpts2d[1, 2] = np.nan  # not seen: stays q4, 65535, and comes back NaN
    msg = wire.detections_to_msg(dets, keypoints="q4")
    assert "kpts2d_q4" in [f.name for f in msg.fields]
    back = wire.msg_to_detections(msg, TOPIC)
    assert np.isnan(back.kpts2d[1, 2]).all() and np.isfinite(back.kpts2d[1, :2]).all()
    np.testing.assert_allclose(back.kpts2d[0], dets.kpts2d[0], atol=1 / 32)
    msg = _q4_message()
    rec = np.frombuffer(msg.data, dtype=np.uint8).copy()
    off = next(f.offset for f in msg.fields if f.name == "kpts2d_q4") + msg.point_step
    rec[off:off + 2] = 255  # detection 1, keypoint 0 u = 65535: not seen
    msg.data = rec.tobytes()
    back = wire.msg_to_detections(msg, TOPIC)
    assert np.isnan(back.kpts2d[1, 0, 0]) and np.isfinite(back.kpts2d[0]).all()
    with pytest.raises(ValueError, match="vertices: expected one of"):
        wire.detections_to_msg(make_dets(1, 1, 1), vertices="q8")


def test_q4_layout_errors():
    msg = _q4_message()
    msg.fields = list(msg.fields) + [PointField(name="verts2d", offset=0, datatype=7, count=8)]
    with pytest.raises(wire.WireError, match="both 'verts2d' and 'verts2d_q4'") as e:
        wire.msg_to_detections(msg, TOPIC)
    assert e.value.reason == "duplicate_field"
    msg = _q4_message()
    for f in msg.fields:
        if f.name == "verts2d_q4":
            f.datatype = PointField.FLOAT32
            f.count = 4
    with pytest.raises(wire.WireError, match="verts2d_q4: datatype FLOAT32, expected UINT16"):
        wire.msg_to_detections(msg, TOPIC)


def test_announced_subset_round_trip_and_errors():
    full = make_dets(3, 2, 100, verts=(0.0, 1000.0))
    sub = full.with_vertex_subset(3, 10)
    assert sub.mesh_subset == (100, 3, 10) and sub.num_vertices == 10 and sub.mesh_vertices == 100
    np.testing.assert_array_equal(sub.verts2d, full.verts2d[:, epipolar.vertex_subset(100, 3, 10)])
    for layout in ("f32", "q4"):
        back = wire.msg_to_detections(roundtrip(wire.detections_to_msg(sub, layout)), TOPIC)
        assert back.mesh_subset == (100, 3, 10)
        np.testing.assert_array_equal(back.vertex_ids, epipolar.vertex_subset(100, 3, 10))
    # the frontend's stride, then a count on top of it
    assert full.with_vertex_subset(3).with_vertex_subset(3, 10).mesh_subset == (100, 3, 10)
    with pytest.raises(ValueError, match="does not contain"):
        sub.with_vertex_subset(2)
    with pytest.raises(ValueError, match="the whole mesh was asked for"):
        sub.with_vertex_subset(1)
    msg = wire.detections_to_msg(sub)
    data = np.frombuffer(msg.data, dtype=np.uint8).copy()
    off = next(f.offset for f in msg.fields if f.name == wire.SUBSET_FIELD)
    data[off + 4:off + 8] = np.frombuffer(np.uint32(4).tobytes(), np.uint8)  # detection 0 stride 4
    bad = wire.detections_to_msg(sub)
    bad.data = data.tobytes()
    with pytest.raises(wire.WireError, match="verts2d_subset: detection 1 announces") as e:
        wire.msg_to_detections(bad, TOPIC)
    assert e.value.reason == "bad_subset"
    one = wire.detections_to_msg(sub.select(np.array([0])))
    data = np.frombuffer(one.data, dtype=np.uint8).copy()
    data[off + 8:off + 12] = 0  # count 0: every 3rd of 100 vertices
    one.data = data.tobytes()
    with pytest.raises(wire.WireError, match="selects 34 vertices, verts2d has 10"):
        wire.msg_to_detections(one, TOPIC)


@pytest.fixture
def isfinite_calls(monkeypatch) -> list:
    """Grows by one entry per np.isfinite call (validation's pass over the arrays) from the
    test's start."""
    calls = []
    original = np.isfinite

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(np, "isfinite", spy)
    return calls


def test_f32_verts_view_the_message_and_are_validated_once(isfinite_calls):
    dets = make_dets(3, 4, 600, verts=(0.0, 1000.0))
    msg = roundtrip(wire.detections_to_msg(dets))
    back = wire.msg_to_detections(msg, TOPIC)
    rows = epipolar.point_rows(back.verts2d)
    assert np.shares_memory(rows.flat, np.frombuffer(msg.data, dtype=np.uint8))  # zero copy
    calls = isfinite_calls
    calls.clear()  # the decoder's own checks
    back.validate()
    assert calls == []  # marked validated by the decoder: no second pass over the arrays
    replaced = FrameDetections(back.camera, back.stamp_ns, back.bboxes, back.scores, back.kpts2d,
                               back.kpts3d, back.verts2d.copy())
    replaced.validate()
    assert calls  # a new object (or a replaced array) is checked
    calls.clear()
    replaced.validate()
    assert calls == []
    replaced.bboxes = replaced.bboxes.copy()
    replaced.validate()
    assert calls




@pytest.fixture(scope="module")
def bench_frames():
    rig = load_rig("sportcenter6")
    rng = np.random.default_rng(3)
    template = body_template(2000, 70, 3)
    return rig, [make_frame(rig, template, rng, 6, 2, stamp_ns=k) for k in range(2)]


def _decoded(frames, **encode):
    return {c: wire.msg_to_detections(roundtrip(wire.detections_to_msg(fd, **encode)), f"/{c}/d")
            for c, fd in frames.items()}


def _members(result):
    return [c.members.tolist() for c in result.clusters]


def test_f32_and_q4_give_the_same_clusters(bench_frames):
    rig, load = bench_frames
    params = AssociationParams.from_mapping(load_node_params("sportcenter.yaml", "association"))
    for fr in load:
        f32 = associate(rig, _decoded(fr.frames), params)
        q4 = associate(rig, _decoded(fr.frames, vertices="q4", keypoints="q4"), params)
        assert _members(f32) == _members(q4)
        assert len(f32.clusters) == 6
        assert f32.stats["rejected_epipolar"] == q4.stats["rejected_epipolar"]


def test_a_subset_announced_on_the_wire_is_honoured(bench_frames):
    rig, load = bench_frames
    base = load_node_params("sportcenter.yaml", "association")
    fr = load[0]
    sent = {c: fd.with_vertex_subset(8) for c, fd in fr.frames.items()}
    got = _decoded(sent, vertices="q4")
    assert all(fd.mesh_subset == (2000, 8, 0) for fd in got.values())
    on_wire = associate(rig, got, AssociationParams.from_mapping(base))
    local = associate(rig, fr.frames, AssociationParams.from_mapping({**base, "vertex_stride": 8}))
    assert _members(on_wire) == _members(local)
    assert on_wire.stats["rejected_epipolar"] == local.stats["rejected_epipolar"]
    # the association's own subset applies on the full mesh ids: stride 16 of the full mesh is
    # every 2nd vertex of a stride-8 message
    both = associate(rig, got, AssociationParams.from_mapping({**base, "vertex_stride": 16}))
    ref = associate(rig, fr.frames, AssociationParams.from_mapping({**base, "vertex_stride": 16}))
    assert _members(both) == _members(ref)
    # one camera sends the whole mesh, the others a subset: compared on the common vertices
    mixed = dict(got, **{rig.names[0]: fr.frames[rig.names[0]]})
    assert _members(associate(rig, mixed, AssociationParams.from_mapping(base))) == _members(local)


def test_a_subset_of_validated_detections_is_not_checked_again(isfinite_calls):
    """The track stage hands the association the detections it left: rows of a validated frame
    need no second pass; rows of an unchecked frame still get one."""
    back = wire.msg_to_detections(roundtrip(wire.detections_to_msg(make_dets(3, 4, 600))), TOPIC)
    calls = isfinite_calls
    calls.clear()  # the decoder's own checks
    back.select(np.array([0, 2])).validate()
    assert calls == []
    unchecked = FrameDetections(back.camera, back.stamp_ns, back.bboxes, back.scores,
                                back.kpts2d, back.kpts3d, back.verts2d.copy())
    unchecked.select(np.array([1])).validate()
    assert calls
