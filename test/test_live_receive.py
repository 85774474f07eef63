"""The association node's receive path (issue 14): serialized detections taken raw and decoded
in place, every pending message taken before the synchroniser decides, rmw receive times."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from rclpy.duration import Duration
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2

from maem_ros.core.association import AssociationParams, PairGates
from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.limits import InputLimits, LimitError, _first_outside, check_detections
from maem_ros.ros import wire
from maem_ros.ros.association_node import WARM_FRAMES
from maem_ros.ros.intake import QueuedArrival, arrival_ns

from helpers_ros import stall, start_pipeline, wait_for


def test_busy_node_takes_every_pending_message_before_a_set_goes_partial(graph, scene):
    """While the executor is blocked, three frames of all six cameras reach the node's DDS
    queues (acknowledged) and wait there far longer than max_wait. Once the node runs again its
    poll timer is served first; taking every pending message before deciding, all three sets
    are complete (keep_every_set: all three are processed, though stale)."""
    g = start_pipeline(graph, association={"max_wait": 0.001, "poll_period": 0.005,
                                           "keep_every_set": True})
    release = threading.Event()
    started = stall(graph, release)
    assert wait_for(started.is_set, 10.0)
    cams = g["assoc"].rig.names
    try:
        for f in range(3):
            for cam in cams:
                g["player"].publish(scene.detections(cam, f))
        for pub in g["player"].pubs.values():
            assert pub.wait_for_all_acked(Duration(seconds=10))
    finally:
        release.set()
    stamps = [scene.stamp_ns(f) for f in range(3)]
    assert wait_for(lambda: all(g["clusters"].has(s) for s in stamps), 20.0, graph)
    d = g["diags"]
    d.wait_value("/association", "count/sync_sets", lambda v: v == 3, graph=graph)
    kv = d.get("/association")
    assert kv.get("count/sync_partial_sets", "0") == "0", kv
    assert kv["frames_dropped"] == "0" and int(kv["received/camera_0/detections"]) == 3, kv
    assert {int(c) for c in g["clusters"].by_stamp[stamps[0]].camera} == set(range(len(cams)))


@pytest.mark.parametrize("keep_every_set", [False, True])
def test_node_that_fell_behind_skips_the_stale_sets_by_default(graph, scene, keep_every_set):
    """Five frames (30 fps stamps) wait 0.4 s while the executor is blocked: beyond the
    default backlog bound (4 frame periods, 133 ms), so the node processes only the newest and
    counts four dropped/behind, instead of working through all five at growing latency; with
    keep_every_set (a replay that wants every frame) it processes all five."""
    g = start_pipeline(graph, association={"keep_every_set": keep_every_set})
    assert g["assoc"].backlog.policy.params.keep_every_set is keep_every_set
    release = threading.Event()
    started = stall(graph, release)
    assert wait_for(started.is_set, 10.0)
    period = 33_333_333
    stamp = lambda f: scene.stamp_ns(0) + f * period  # noqa: E731 - 30 fps stamps
    try:
        for f in range(5):
            for cam in g["assoc"].rig.names:
                dets = scene.detections(cam, f)
                dets.stamp_ns = stamp(f)
                g["player"].publish(dets)
        for pub in g["player"].pubs.values():
            assert pub.wait_for_all_acked(Duration(seconds=10))
        time.sleep(0.4)
    finally:
        release.set()
    assert wait_for(lambda: g["clusters"].has(stamp(4)), 20.0, graph)
    d = g["diags"]
    processed = 5 if keep_every_set else 1
    d.wait_value("/association", "frames_processed", lambda v: v == processed, graph=graph)
    assert d.value("/association", "dropped/behind") == 5 - processed
    assert sorted(g["clusters"].by_stamp) == [stamp(f) for f in range(5 - processed, 5)]
    kv = d.get("/association")
    assert kv["backlog/policy"] == ("keep every set" if keep_every_set else "skip stale"), kv
    d.wait_value("/association", "behind/episodes", lambda v: v >= 1, graph=graph)


@pytest.mark.parametrize("light_when_late", [True, False])
def test_frame_sets_that_waited_beyond_a_frame_period_run_the_light_step(graph, scene, light_when_late):
    """Tracks from four frames at 30 fps stamps; then two frame sets wait 0.1 s while the
    executor is blocked: late (more than a frame period) but within the backlog bound (2 s
    here), so both are processed, with the track stage's light step (counted light_steps; new
    people deferred, counted new_deferred, so q4 messages are decoded without their mesh), and
    nothing is skipped; with light_when_late false both run the full step."""
    # light_load 1: only the sets that waited run light (the test's own pace may load the node)
    g = start_pipeline(graph, association={"light_when_late": light_when_late, "keep_every_set": False,
                                           "max_backlog": 2.0, "light_load": 1.0})
    cams = g["assoc"].rig.names
    stamp = lambda f: scene.stamp_ns(0) + f * 33_333_333  # noqa: E731 - 30 fps stamps

    def publish(f: int) -> None:
        for cam in cams:
            dets = scene.detections(cam, f)
            dets.stamp_ns = stamp(f)
            g["player"].publish(dets)

    for f in range(4):
        publish(f)
        assert wait_for(lambda: g["clusters"].has(stamp(f)), 20.0, graph)
    release = threading.Event()
    started = stall(graph, release)
    assert wait_for(started.is_set, 10.0)
    try:
        for f in (4, 5):
            publish(f)
        for pub in g["player"].pubs.values():
            assert pub.wait_for_all_acked(Duration(seconds=10))
        time.sleep(0.1)
    finally:
        release.set()
    assert wait_for(lambda: g["clusters"].has(stamp(5)), 20.0, graph)
    d = g["diags"]
    d.wait_value("/association", "frames_processed", lambda v: v == 6, graph=graph)
    assert d.value("/association", "dropped/behind") == 0
    assert d.value("/association", "count/light_steps") == (2 if light_when_late else 0)
    # both within light_new_every (0.1 s) of the last full step: no association of new people
    assert d.value("/association", "count/new_deferred") == (2 if light_when_late else 0)
    assert g["clusters"].has(stamp(4)) and len(g["clusters"].by_stamp[stamp(5)].cluster) > 0


@pytest.mark.parametrize("light_load", [0.0, 1.0])
def test_a_loaded_node_runs_the_light_step_before_any_set_waited(graph, scene, light_load):
    """light_load: the light step also runs while the node's load (its callbacks' share of
    the last 0.25 s, /diagnostics load) is above it. At 0 any load is above it: every set with
    tracks (all but the first) runs light although none waited; at 1 (the load never exceeds
    it) none does. /diagnostics shows the load."""
    g = start_pipeline(graph, association={"keep_every_set": False, "light_load": light_load})
    cams = g["assoc"].rig.names
    stamp = lambda f: scene.stamp_ns(0) + f * 33_333_333  # noqa: E731 - 30 fps stamps
    for f in range(4):
        for cam in cams:
            dets = scene.detections(cam, f)
            dets.stamp_ns = stamp(f)
            g["player"].publish(dets)
        assert wait_for(lambda: g["clusters"].has(stamp(f)), 20.0, graph)
    d = g["diags"]
    d.wait_value("/association", "frames_processed", lambda v: v == 4, graph=graph)
    assert d.value("/association", "count/light_steps") == (3 if light_load == 0.0 else 0)
    assert d.value("/association", "dropped/behind") == 0
    assert 0.0 < float(d.get("/association")["load"]) <= 1.0
    assert all(len(g["clusters"].by_stamp[stamp(f)].cluster) > 0 for f in range(4))


def test_raw_detections_garbage_is_dropped_as_bad_cdr_and_the_node_goes_on(graph, scene):
    """Bytes that are no serialized PointCloud2 (published as a PointCloud2 whose CDR is cut)
    are counted under bad_cdr; the next frame goes through."""
    g = start_pipeline(graph)
    pub = g["player"].pubs["camera_0"]
    msg = wire.detections_to_msg(scene.detections("camera_0", 0))
    data = bytes(serialize_message(msg))
    pub.publish(data[:200])  # rclpy publishes serialized bytes as they are
    g["diags"].wait_value("/association", "dropped/bad_cdr", lambda v: v == 1, graph=graph)
    for cam in g["assoc"].rig.names:
        g["player"].publish(scene.detections(cam, 1))
    assert wait_for(lambda: g["poses"].has(scene.stamp_ns(1)), 20.0, graph)


def test_cdr_decoder_reads_the_payload_in_place(scene):
    """cdr_to_cloud + msg_to_detections: the same detections as rclpy's deserialisation, the
    vertices a view of the received bytes."""
    from rclpy.serialization import deserialize_message
    dets = scene.detections("camera_2", 4)
    for layout in wire.WIRE_VERTICES:
        data = bytes(serialize_message(wire.detections_to_msg(dets, layout)))
        fast = wire.msg_to_detections(wire.cdr_to_cloud(data, "/t"), "/t")
        ref = wire.msg_to_detections(deserialize_message(data, PointCloud2), "/t")
        assert fast.stamp_ns == ref.stamp_ns and fast.camera == ref.camera
        for name in ("bboxes", "scores", "kpts2d", "kpts3d", "verts2d"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name))
    fast = wire.msg_to_detections(wire.cdr_to_cloud(data := bytes(serialize_message(
        wire.detections_to_msg(dets))), "/t"), "/t")
    assert np.shares_memory(fast.verts2d, np.frombuffer(data, np.uint8))
    for bad in (b"", b"\x00\x01\x00\x00", data[: len(data) // 2]):
        with pytest.raises(wire.WireError) as e:
            wire.cdr_to_cloud(bad, "/camera_2/detections")
        assert e.value.reason == "bad_cdr" and "/camera_2/detections: data:" in str(e.value)


def test_arrival_is_now_minus_the_time_in_the_queue() -> None:
    import time
    now = 5_000_000_000
    waited = 0.2e9
    info = {"received_timestamp": time.time_ns() - int(waited)}
    got = arrival_ns(now, info)
    assert now - waited - 0.5e9 < got <= now - waited  # within the time this line took
    assert arrival_ns(now, {"received_timestamp": time.time_ns() + 10**9}) == now
    assert arrival_ns(now, {}) == now and arrival_ns(now, None) == now


def test_queued_arrival_sees_time_queued_before_the_reader_history(monkeypatch) -> None:
    """A message that took 80 ms more than the topic's fastest recent delivery (queued on the
    way: a shared-memory port, a starved receive thread) counts as arrived 80 ms ago, though
    the rmw stamped it received just now; a constant transit (network, clock offset) does
    not; the baseline is per topic and forgets after WINDOW_NS."""
    wall = [10**18]
    monkeypatch.setattr(time, "time_ns", lambda: wall[0])
    q, now, ms = QueuedArrival(), 5 * 10**12, 10**6

    def arrive(topic: str, transit_ms: float, waited_ms: float = 0.0) -> int:
        info = {"source_timestamp": wall[0] - int(transit_ms * ms),
                "received_timestamp": wall[0] - int(waited_ms * ms)}
        return q.arrival_ns(topic, now, info)

    assert arrive("/a", 500) == now  # the first message sets the baseline (500 ms offset)
    assert arrive("/a", 503) == now - 3 * ms
    assert arrive("/a", 580, waited_ms=20) == now - 80 * ms
    assert arrive("/a", 580, waited_ms=95) == now - 95 * ms  # the reader history's wait
    assert arrive("/b", 580) == now  # another topic: its own baseline
    wall[0] += QueuedArrival.WINDOW_NS + ms  # the old baseline is forgotten
    assert arrive("/a", 580) == now
    assert q.arrival_ns("/a", now, {"received_timestamp": wall[0]}) == now  # no source stamp


@pytest.mark.parametrize("margin", [0.0, 0.3, 1.0])
def test_pixel_limits_fast_path_agrees_with_the_elementwise_check(margin: float) -> None:
    """The reductions that accept a message decide as the elementwise comparison does: per
    axis (x against width, y against height), NaN ignored, the first offending value named."""
    rng = np.random.default_rng(7)
    lo, hi = -margin * np.array([1920.0, 1080.0]), (1 + margin) * np.array([1920.0, 1080.0])
    for trial in range(300):
        pts = rng.uniform(-0.2, 1.2, (3, 50, 2)).astype(np.float32) * np.float32([1920, 1080])
        pts[rng.random(pts.shape) < 0.1] = np.nan
        if trial % 3 == 0:
            pts = np.clip(pts, lo, hi).astype(np.float32)
        if trial % 7 == 0:
            pts[:] = np.nan
        with np.errstate(invalid="ignore"):
            bad = (pts < lo) | (pts > hi)
        want = float(pts[bad].flat[0]) if bad.any() else None
        assert _first_outside(pts, lo, hi) == want


def _received(dets, layout: str = "f32"):
    return wire.cdr_to_cloud(bytes(serialize_message(wire.detections_to_msg(dets, layout))), "/t")


@pytest.mark.parametrize("layout", ["f32", "q4"])
def test_receive_check_prepares_f32_frames_in_the_pass_that_checks_them(scene, layout) -> None:
    """checked_detections: an f32 message whose vertices the gates prepare comes back as the
    prepared, validated frame (the preparing pass is the vertex check); a q4 one stays encoded
    until its set is processed. Either way the frame is the reader's, and gated alike."""
    from maem_ros.ros.association_node import checked_detections, prepared_detections

    gates = PairGates(scene.rig, AssociationParams())
    assert gates.prepare_strides()  # the default params screen: prepare makes its pass
    cloud = _received(scene.detections("camera_1", 2), layout)
    item = checked_detections(cloud, "/t", "camera_1", scene.rig, InputLimits(), gates)
    assert isinstance(item, FrameDetections) == (layout == "f32")
    if layout == "f32":
        assert gates.is_prepared(item) and item._is_validated()
    frame = prepared_detections(item, gates)
    assert gates.is_prepared(frame) and frame._is_validated()
    ref = wire.msg_to_detections(cloud, "/t")
    for name in ("bboxes", "scores", "kpts2d", "kpts3d", "verts2d"):
        np.testing.assert_array_equal(getattr(frame, name), getattr(ref, name))


def test_a_q4_message_decoded_without_its_mesh_keeps_every_other_field(scene) -> None:
    """prepared_detections(..., vertices=False), for a light step that reads no vertex
    (TemporalAssociator.associates_new): no vertex and no mesh subset, not prepared, validated,
    every other field as the reader decodes it."""
    from maem_ros.ros.association_node import checked_detections, prepared_detections

    gates = PairGates(scene.rig, AssociationParams())
    cloud = _received(scene.detections("camera_1", 2), "q4")
    item = checked_detections(cloud, "/t", "camera_1", scene.rig, InputLimits(), gates)
    frame = prepared_detections(item, gates, vertices=False)
    ref = wire.msg_to_detections(cloud, "/t")
    assert frame.verts2d.shape == (ref.n, 0, 2) and frame.mesh_subset is None and ref.verts2d.shape[1] > 0
    assert not gates.is_prepared(frame) and frame._is_validated()
    for name in ("bboxes", "scores", "kpts2d", "kpts3d"):
        np.testing.assert_array_equal(getattr(frame, name), getattr(ref, name))


def test_receive_check_of_f32_vertices_rejects_as_the_reader_does(scene) -> None:
    """With the check in the gates' pass, an inf vertex is refused with the reader's own error
    (nonfinite, the detection named), a vertex beyond the image by the pixel limits; with
    params under which the gates make no pass (vertex_stride 2) the reader checks."""
    from maem_ros.ros.association_node import checked_detections

    rig: Rig = scene.rig
    for params in (AssociationParams(), AssociationParams(vertex_stride=2)):
        gates = PairGates(rig, params)
        dets = scene.detections("camera_1", 2)
        dets.verts2d = dets.verts2d.copy()
        dets.verts2d[2, 11, 0] = np.inf
        dets.verts2d[0, :40] = np.nan  # missing vertices are fine
        with pytest.raises(wire.WireError) as got:
            checked_detections(_received(dets), "/t", "camera_1", rig, InputLimits(), gates)
        with pytest.raises(wire.WireError) as want:
            wire.read_detections(_received(dets), "/t")
        assert (got.value.reason, str(got.value)) == ("nonfinite", str(want.value))
        assert "inf in detection 2" in str(got.value)
        dets.verts2d[2, 11, 0] = -3.5 * rig["camera_1"].width
        with pytest.raises(LimitError, match="verts2d"):
            checked_detections(_received(dets), "/t", "camera_1", rig, InputLimits(), gates)
        dets.verts2d[2, 11, 0] = 5.0
        item = checked_detections(_received(dets), "/t", "camera_1", rig, InputLimits(), gates)
        assert isinstance(item, FrameDetections) == bool(gates.prepare_strides())


def test_an_inf_vertex_is_dropped_as_nonfinite_and_the_node_goes_on(graph, scene):
    """Through the node: a full-mesh f32 message with an inf vertex is counted under
    nonfinite, the next frame goes through."""
    g = start_pipeline(graph)
    dets = scene.detections("camera_0", 0)
    dets.verts2d = dets.verts2d.copy()
    dets.verts2d[1, 5, 1] = -np.inf
    g["player"].publish(dets)
    g["diags"].wait_value("/association", "dropped/nonfinite", lambda v: v == 1, graph=graph)
    for cam in g["assoc"].rig.names:
        g["player"].publish(scene.detections(cam, 1))
    assert wait_for(lambda: g["poses"].has(scene.stamp_ns(1)), 20.0, graph)


def test_pixel_limits_on_a_strided_vertex_view(scene) -> None:
    """A decoded f32 message (vertices a strided view of the payload): in bounds passes; one
    vertex beyond the image by more than the margin is named."""
    rig: Rig = scene.rig
    dets = scene.detections("camera_1", 2)
    fd = wire.msg_to_detections(wire.cdr_to_cloud(bytes(serialize_message(
        wire.detections_to_msg(dets))), "/t"), "/t")
    assert not fd.verts2d.flags["C_CONTIGUOUS"]
    check_detections(fd, rig, InputLimits(), "/t")
    far = dets.verts2d.copy()
    far[1, 17, 1] = 3.5 * rig["camera_1"].height
    dets.verts2d = far
    fd = wire.msg_to_detections(wire.cdr_to_cloud(bytes(serialize_message(
        wire.detections_to_msg(dets))), "/t"), "/t")
    with pytest.raises(LimitError, match="verts2d"):
        check_detections(fd, rig, InputLimits(), "/t")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(12, 2 * 3000), (3, 10), (0, 8), (2, 0)])
def test_q4_decode_equals_the_straightforward_formula(dtype, shape) -> None:
    """decode_q4 (cast, scale in place, origin as one complex add) gives the same bits as
    code / 16 + origin per (u, v) with NaN for 65535, on a strided field view too."""
    rng = np.random.default_rng(shape[0] * 7 + shape[1])
    code = rng.integers(0, 65536, shape).astype(np.uint16)
    code[rng.random(shape) < 0.05] = wire.Q4_MISSING
    origin = np.floor(rng.uniform(-300, 3000, (shape[0], 2))).astype(np.float32)
    want = np.multiply(code, dtype(1.0 / wire.Q4_SCALE), dtype=dtype)
    if want.size:
        want.reshape(shape[0], -1, 2)[:] += origin[:, None, :].astype(dtype)
    want[code == wire.Q4_MISSING] = np.nan
    strided = np.zeros((shape[0], shape[1] + 3), np.uint16)[:, 1:shape[1] + 1]
    strided[:] = code
    for src in (code, strided):
        got = wire.decode_q4(src, dtype, origin)
        assert got.dtype == dtype and np.array_equal(got, want, equal_nan=True)
    plain = wire.decode_q4(code, dtype)
    assert np.array_equal(plain, np.where(code == wire.Q4_MISSING, np.nan,
                                          code.astype(dtype) / dtype(16)), equal_nan=True)


def test_bench_live_rejects_a_negative_vertex_count() -> None:
    import subprocess
    import sys
    proc = subprocess.run([sys.executable, "-m", "maem_ros.tools.bench.bench", "--live",
                           "--vertex-count", "-1"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--vertex-count" in proc.stderr, proc.stderr


def test_poll_timer_runs_only_while_a_set_waits(graph, scene):
    """With nothing queued the node's poll timer is off (no empty wake-ups); one camera's
    message arms it, and a set missing cameras still goes out after max_wait, partial."""
    g = start_pipeline(graph, association={"max_wait": 0.2, "poll_period": 0.01})
    node = g["assoc"]
    assert wait_for(node.timer.is_canceled, 10.0, graph), "poll timer runs with nothing queued"
    for cam in node.rig.names[:3]:
        g["player"].publish(scene.detections(cam, 0))
    assert wait_for(lambda: not node.timer.is_canceled() or g["clusters"].has(scene.stamp_ns(0)),
                    10.0, graph), "a queued message did not arm the poll timer"
    assert wait_for(lambda: g["clusters"].has(scene.stamp_ns(0)), 10.0, graph)
    g["diags"].wait_value("/association", "count/sync_partial_sets", lambda v: v == 1,
                          graph=graph)
    assert wait_for(node.timer.is_canceled, 10.0, graph), "poll timer left running"
    assert {int(c) for c in g["clusters"].by_stamp[scene.stamp_ns(0)].camera} <= {0, 1, 2}


@pytest.mark.ros
def test_executor_choice_and_a_bad_one(monkeypatch) -> None:
    """MAEM_EXECUTOR picks the nodes' executor; anything else is a one-line ConfigError."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from maem_ros.ros.params import ConfigError
    from maem_ros.ros.process import EXECUTOR_VAR, make_executor
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        monkeypatch.setenv(EXECUTOR_VAR, "single")
        single = make_executor(ctx)
        assert isinstance(single, SingleThreadedExecutor)
        monkeypatch.setenv(EXECUTOR_VAR, "events")
        events = make_executor(ctx)
        assert type(events).__name__ == "EventsExecutor"
        for ex in (single, events):
            ex.shutdown(timeout_sec=1.0)
        monkeypatch.setenv(EXECUTOR_VAR, "threads")
        with pytest.raises(ConfigError, match="MAEM_EXECUTOR='threads'.*'single', 'events'"):
            make_executor(ctx)
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize("variable,value,node", [
    ("MAEM_EXECUTOR", "threads", "association_node"),
    ("MAEM_HEAP_PREFAULT_MB", "lots", "triangulation_node")])
@pytest.mark.ros
def test_node_with_a_bad_environment_setting_exits_2_with_one_line(variable, value, node) -> None:
    import os
    import subprocess
    import sys

    env = dict(os.environ, **{variable: value})
    proc = subprocess.run([sys.executable, "-m", f"maem_ros.ros.{node}", "--ros-args",
                           "-p", "rig:=sportcenter6"], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if "invalid configuration" in line]
    assert len(errors) == 1 and f"{variable}={value!r}" in errors[0], proc.stderr


def test_freed_memory_is_kept_for_reuse() -> None:
    """On glibc the nodes set the mmap / trim thresholds (mallopt accepts both values)."""
    import platform

    from maem_ros.ros.process import keep_freed_memory
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_freed_memory()


_FAULTS_OF_A_NEW_BUFFER = """
import resource, sys
import numpy as np
from maem_ros.ros.process import keep_freed_memory
assert keep_freed_memory(int(sys.argv[1]))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
buf = np.empty(1_800_000, np.uint8)  # what a node does per message: a fresh ~1.8 MB buffer
buf.fill(1)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.parametrize("prefault_mb", [0, 32])
def test_prefaulted_heap_serves_a_new_message_buffer_without_page_faults(prefault_mb) -> None:
    """The first 1.8 MB buffer (a full-mesh message) allocated after keep_freed_memory(N MiB)
    lands on pages the prefault already touched: ~0 page faults, where a process that did not
    prefault faults its ~440 pages in (1.8 MB / 4 KiB, the kernel maps each on first write)."""
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    out = subprocess.run([sys.executable, "-c", _FAULTS_OF_A_NEW_BUFFER, str(prefault_mb)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    faults = int(out.stdout.strip())
    assert (faults >= 400) if prefault_mb == 0 else (faults <= 20), faults


def test_the_node_runs_its_path_warm_before_it_subscribes_and_keeps_no_trace_of_it(graph, scene):
    """At start the node ran its own path on simulated frame sets of its rig (WARM_FRAMES in
    each wire layout: no tracks, the full step, the light step) with a throwaway track stage: its own stage has no tracks and no stamp,
    nothing is counted, and the first real frame set gets clusters like any other."""
    g = start_pipeline(graph)
    assoc = g["assoc"]
    assert assoc.warm_sets == WARM_FRAMES * len(wire.WIRE_VERTICES) == 6
    assert assoc.temporal.tracker.tracks == [] and assoc.temporal._last_stamp is None
    for cam in assoc.rig.names:
        g["player"].publish(scene.detections(cam, 0))
    assert wait_for(lambda: g["clusters"].has(scene.stamp_ns(0)), 20.0, graph)
    g["diags"].wait_value("/association", "count/sync_sets", lambda v: v == 1, graph=graph)
    kv = g["diags"].get("/association")
    assert kv["frames_dropped"] == "0", kv
    assert len(g["clusters"].by_stamp[scene.stamp_ns(0)].cluster) > 0


def _kernel_signatures() -> dict[str, int]:
    """How many type signatures each loaded maem_ros numba kernel has compiled or loaded."""
    import sys

    from numba.core.registry import CPUDispatcher

    return {f"{name}.{k}": len(v.signatures) for name, mod in list(sys.modules.items())
            if name.startswith("maem_ros") for k, v in vars(mod).items()
            if isinstance(v, CPUDispatcher)}


@pytest.mark.parametrize("layout", wire.WIRE_VERTICES)
def test_the_first_real_frame_set_loads_no_kernel(scene, layout):
    """The warm pass ran every kernel with the argument types real messages bring, whether
    the executor hands them over as writable arrays (ros.raw_take) or as bytes: the first
    real frame sets load nothing from numba's cache (a q4 decoder compiled for read-only
    fields once did, on the stream's first frame)."""
    import rclpy
    from rclpy.parameter import Parameter

    from maem_ros.ros.association_node import AssociationNode
    from helpers_ros import pipeline_params

    pytest.importorskip("numba")
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = AssociationNode(context=context, parameter_overrides=[
            Parameter(k, value=v) for k, v in pipeline_params()[0].items()])
        published: list = []
        node.pub.publish = published.append  # no executor here: what would go out
        before = _kernel_signatures()
        for f, as_array in ((0, True), (1, False), (2, True)):
            for cam in node.rig.names:
                data = serialize_message(wire.detections_to_msg(scene.detections(cam, f), layout, layout))
                node._receive(cam, f"/{cam}/detections", np.frombuffer(data, np.uint8).copy()
                              if as_array else data, None)
            node._decide()
        assert len(published) == 3  # each set processed, none dropped
        after = _kernel_signatures()
        assert {k: (before.get(k), n) for k, n in after.items() if n != before.get(k)} == {}
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
