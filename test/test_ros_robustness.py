"""Nodes keep running on bad input and count every dropped frame with its reason (/diagnostics).

Silent camera, stamps jumping backwards, malformed PointCloud2, unknown camera frame_id, empty
frames, bad images, and invalid parameters (exit code 2, one line).
"""
from __future__ import annotations

import array
import os
import subprocess
import sys

import numpy as np
import pytest
from sensor_msgs.msg import Image, PointCloud2, PointField

from maem_ros.core.detections import FrameDetections
from maem_ros.ros import wire
from maem_ros.ros.qos import DATA_QOS, IMAGE_QOS

from helpers_ros import DiagnosticsReader, Recorder, bad_messages, play, start_pipeline, wait_for

# node graphs fed bad input
pytestmark = [pytest.mark.timeout(150), pytest.mark.ros]


def test_silent_camera_is_reported_and_picked_up_again(graph, scene):
    g = start_pipeline(graph, association=dict(max_wait=0.8))
    cams = g["assoc"].rig.names
    silent = cams[-1]
    k_silent = cams.index(silent)

    def active(f: int) -> list[str]:
        # silent for frames 3..6; when it returns its message comes first (a set emitted just
        # before it arrives would rightly drop it as late, which this test does not depend on)
        return cams[:-1] if 3 <= f <= 6 else [silent] + cams[:-1]

    stamps = play(g, scene, range(10), cameras=active)
    assert wait_for(lambda: all(g["clusters"].has(s) for s in stamps), 15.0, graph), \
        [g["clusters"].has(s) for s in stamps]
    for f, stamp in enumerate(stamps):
        cf = g["clusters"].by_stamp[stamp]
        assert len(cf.camera) > 0
        assert (k_silent in cf.camera) == (silent in active(f)), f"frame {f}: {set(cf.camera)}"
    d = g["diags"]
    d.wait_value("/association", f"missing/{silent}", lambda v: v == 4, graph=graph)
    d.wait_value("/association", "frames_processed", lambda v: v == 10, graph=graph)
    assert d.get("/association")["frames_dropped"] == "0"
    assert wait_for(lambda: all(g["poses"].has(s) for s in stamps), 10.0, graph)


def test_stamps_jumping_backwards_reset_sync_and_tracker(graph, scene):
    g = start_pipeline(graph)
    order = list(range(6)) + list(range(0, 4))  # a bag loop: back to frame 0 after frame 5
    play(g, scene, order)
    assert wait_for(lambda: g["poses"].count() >= len(order), 15.0, graph), g["poses"].count()
    d = g["diags"]
    d.wait_value("/association", "count/sync_resets", lambda v: v >= 1, graph=graph)
    d.wait_value("/triangulation", "count/tracker_resets", lambda v: v == 1, graph=graph)
    d.wait_value("/association", "count/track_resets", lambda v: v == 1, graph=graph)  # temporal
    d.wait_value("/triangulation", "frames_processed", lambda v: v == len(order), graph=graph)
    assert [p.stamp_ns for p in g["poses"].all] == [scene.stamp_ns(f) for f in order]
    # after the reset, persons are tentative again: no confirmed id in the first looped frame
    assert np.all(g["poses"].all[6].ids == wire.UNTRACKED_ID)
    # ids are never reused: ids confirmed after the loop are new
    before = {int(i) for p in g["poses"].all[:6] for i in p.ids if i != wire.UNTRACKED_ID}
    after = {int(i) for p in g["poses"].all[6:] for i in p.ids if i != wire.UNTRACKED_ID}
    assert before and after and not (before & after)


def test_malformed_detections_are_dropped_and_counted(graph, scene):
    g = start_pipeline(graph)
    bad = bad_messages(scene)
    for _, msg in bad:
        g["player"].publish_msg("camera_0", msg)
    reasons = [r for r, _ in bad]
    d = g["diags"]
    d.wait_value("/association", "frames_dropped", lambda v: v == len(bad), graph=graph)
    for reason in reasons:
        assert d.get("/association").get(f"dropped/{reason}") == "1", (reason, d.get("/association"))
    # still alive and correct: a full frame goes through
    play(g, scene, [2])
    assert wait_for(lambda: g["poses"].has(scene.stamp_ns(2)), 10.0, graph)
    # malformed clusters reach the triangulation node directly
    pub = g["client"].create_publisher(PointCloud2, "/maem/clusters", DATA_QOS)
    assert wait_for(lambda: pub.get_subscription_count() >= 2, 10.0, graph)
    cl = PointCloud2(height=1, width=2, point_step=4, row_step=8, data=array.array("B", bytes(8)),
                     fields=[PointField(name="cluster", offset=0, datatype=PointField.UINT32,
                                        count=1)])
    cl.header.frame_id = "world"
    pub.publish(cl)
    d.wait_value("/triangulation", "dropped/missing_field", lambda v: v == 1, graph=graph)
    assert d.value("/triangulation", "frames_processed") == 1


def test_empty_frames_flow_through(graph):
    g = start_pipeline(graph)
    cams = g["assoc"].rig.names
    for f in range(3):
        stamp = 1_700_000_000_000_000_000 + f * 33_333_333
        for cam in cams:
            g["player"].publish(FrameDetections.empty(cam, stamp, 70, 2000))
        assert wait_for(lambda: g["poses"].has(stamp), 10.0, graph)
        pf = g["poses"].by_stamp[stamp]
        assert pf.ids.shape == (0,) and pf.joints.shape == (0, 13, 3)
        assert g["clusters"].by_stamp[stamp].cluster.shape == (0,)
    d = g["diags"]
    d.wait_value("/association", "frames_processed", lambda v: v == 3, graph=graph)
    d.wait_value("/triangulation", "frames_processed", lambda v: v == 3, graph=graph)
    assert d.get("/association")["frames_dropped"] == "0"


def _frontend_inputs(transport: str, img: np.ndarray, good: int, after_end: int, other: int):
    """(message type, topic, good message, [bad messages with their drop reason])."""
    import cv2
    from sensor_msgs.msg import CompressedImage

    if transport == "raw":
        truncated = wire.bgr_to_image(img, other, "camera_2")
        truncated.data = truncated.data[:100]
        return Image, "/camera_2/image_raw", wire.bgr_to_image(img, good, "camera_2"), [
            (wire.bgr_to_image(img, after_end, "camera_2"), "estimator"),
            (truncated, "bad_size"),
            (Image(header=truncated.header, height=2, width=2, encoding="32FC1", step=8,
                   data=bytes(16)), "bad_encoding")]

    def jpeg(stamp: int, data: bytes | None = None) -> CompressedImage:
        msg = CompressedImage(format="jpeg", data=data if data is not None else
                              cv2.imencode(".jpg", img)[1].tobytes())
        msg.header = wire.make_header(stamp, "camera_2")
        return msg
    return CompressedImage, "/camera_2/image_raw/compressed", jpeg(good), [
        (jpeg(after_end), "estimator"), (jpeg(other, b""), "bad_size"),
        (jpeg(other, b"\xff\xd8 not a jpeg"), "bad_encoding")]


@pytest.mark.parametrize("transport", ["raw", "compressed"])
def test_frontend_drops_bad_images_and_unknown_stamps(graph, scene, transport):
    from maem_ros.ros.frontend_node import FrontendNode

    cfg = scene.config
    fe = graph.add(FrontendNode, dict(rig="sportcenter6", backend="synthetic", publish_overlay=True,
                                      image_transport=transport, seed=cfg.seed,
                                      difficulty=cfg.difficulty, frames=cfg.frames,
                                      num_vertices=cfg.num_vertices, diagnostics_period=0.2),
                   namespace="/camera_2")
    assert fe.camera_name == "camera_2"
    cam = fe.camera
    img = np.full((cam.height, cam.width, 3), 90, np.uint8)
    stamp = scene.stamp_ns(4)
    after_end = scene.stamp_ns(scene.num_frames - 1) + 1_000_000_000
    msg_type, topic, good, bad = _frontend_inputs(transport, img, stamp, after_end,
                                                  scene.stamp_ns(5))
    client = graph.client("frontend_client")
    pub = client.create_publisher(msg_type, topic, IMAGE_QOS)
    dets = Recorder(client, PointCloud2, "/camera_2/detections", DATA_QOS,
                    lambda m: wire.msg_to_detections(m, "/camera_2/detections", ["camera_2"]))
    overlay = Recorder(client, Image, "/camera_2/detections/overlay", DATA_QOS)
    diags = DiagnosticsReader(client)
    assert wait_for(lambda: pub.get_subscription_count() > 0 and
                    dets.sub.get_publisher_count() > 0, 20.0, graph)
    pub.publish(good)
    assert wait_for(lambda: dets.has(stamp) and overlay.has(stamp), 20.0, graph)
    expect = scene.detections("camera_2", 4)
    np.testing.assert_allclose(dets.by_stamp[stamp].kpts2d, expect.kpts2d, atol=1e-3)
    ov = wire.image_to_bgr(overlay.by_stamp[stamp], "overlay")
    assert ov.shape == img.shape and np.any(ov != ov[0, 0])  # something was drawn
    # one at a time: images are best effort, keep last 2, so a burst may lose frames by design
    for i, (msg, _) in enumerate(bad, start=2):
        pub.publish(msg)
        diags.wait_value("/camera_2/frontend", f"received/{topic.lstrip('/')}", lambda v, i=i: v == i,
                         graph=graph)
    diags.wait_value("/camera_2/frontend", "frames_dropped", lambda v: v == 3, graph=graph)
    got = diags.get("/camera_2/frontend")
    for _, reason in bad:
        assert got[f"dropped/{reason}"] == "1", got
    assert got["frames_processed"] == "1"


ENV = dict(os.environ, PYTHONUNBUFFERED="1")


@pytest.mark.parametrize("node,args,expect", [
    ("association_node", ["-p", "rig:=sportcenter6", "-p", "tau_mesh:=-1.0"], "tau_mesh"),
    ("association_node", ["-p", "rig:=/no/such/rig.yaml"], "rig"),
    ("triangulation_node", ["-p", "rig:=sportcenter6", "-p", "output_convention:=nope"],
     "output_convention"),
    ("frontend_node", ["-p", "rig:=sportcenter6", "-p", "backend:=magic", "-r",
                       "__ns:=/camera_0"], "backend"),
    ("frontend_node", ["-p", "rig:=sportcenter6", "-r", "__ns:=/camera_77"], "camera"),
])
def test_invalid_parameters_exit_2_with_one_line(node, args, expect):
    proc = subprocess.run([sys.executable, "-m", f"maem_ros.ros.{node}", "--ros-args", *args],
                          capture_output=True, text=True, timeout=60, env=ENV)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert "invalid configuration" in lines[0] and f"'{expect}'" in lines[0]
    assert "Traceback" not in proc.stderr


def test_frontend_max_rate_keeps_the_same_stamp_grid(graph, scene):
    from maem_ros.ros.frontend_node import FrontendNode

    cfg = scene.config
    graph.add(FrontendNode, dict(rig="sportcenter6", max_rate=10.0, seed=cfg.seed,
                                 difficulty=cfg.difficulty, frames=cfg.frames,
                                 num_vertices=cfg.num_vertices, diagnostics_period=0.2),
              namespace="/camera_4")
    client = graph.client("rate_client")
    pub = client.create_publisher(Image, "/camera_4/image_raw", IMAGE_QOS)
    dets = Recorder(client, PointCloud2, "/camera_4/detections", DATA_QOS)
    diags = DiagnosticsReader(client)
    assert wait_for(lambda: pub.get_subscription_count() > 0 and
                    dets.sub.get_publisher_count() > 0, 20.0, graph)
    img = np.zeros((2, 2, 3), np.uint8)
    for f in range(7):  # 30 fps stamps; 10 Hz keeps frames 0, 3, 6 (100 ms stamp grid)
        pub.publish(wire.bgr_to_image(img, scene.stamp_ns(f), "camera_4"))
        diags.wait_value("/camera_4/frontend", "received/camera_4/image_raw",
                         lambda v, n=f + 1: v == n, graph=graph)
    assert wait_for(lambda: dets.count() == 3, 10.0, graph)
    assert sorted(dets.by_stamp) == [scene.stamp_ns(f) for f in (0, 3, 6)]
    diags.wait_value("/camera_4/frontend", "count/skipped_max_rate", lambda v: v == 4, graph=graph)
    assert diags.get("/camera_4/frontend")["frames_dropped"] == "0"
