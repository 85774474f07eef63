"""maem-foxglove: a WebSocket client speaking the Foxglove protocol checks the advertised
channels (schema names), that messages arrive and that they decode (protobuf, from the schema
the server advertised) to the bag's / graph's content; plus the scene geometry."""
from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from maem_ros.core.geometry.frames import rig_transforms
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.ros import wire
from maem_ros.viz import scene

from helpers_bags import T0_NS, known_frames, two_camera_rig, write_poses_bag
from helpers_ros import killed_on_exit

BIN = Path(sys.executable).parent
SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01


def expected_schemas(cams) -> dict[str, str]:
    out = {"/maem/skeletons": "foxglove.SceneUpdate", "/maem/rig": "foxglove.SceneUpdate",
           "/tf": "foxglove.FrameTransforms"}
    for c in cams:
        out[f"/{c}/image_raw/compressed"] = "foxglove.CompressedImage"
        out[f"/{c}/camera_info"] = "foxglove.CameraCalibration"
        out[f"/{c}/skeletons_2d"] = "foxglove.ImageAnnotations"
    return out


def message_class(channel: dict):
    """The protobuf class of an advertised channel, built from its FileDescriptorSet schema."""
    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def decode(sdk_msg):
    """A foxglove-sdk message (write-only object) read back through its own protobuf schema."""
    schema = type(sdk_msg).get_schema()
    fds = descriptor_pb2.FileDescriptorSet.FromString(bytes(schema.data))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return cls.FromString(sdk_msg.encode())


class FoxgloveClient:
    """Connects, subscribes to every advertised channel, decodes what arrives (in a thread with
    its own event loop) until ``done(received)`` or the timeout."""

    def __init__(self, url: str):
        self.url = url
        self.channels: dict[str, dict] = {}
        self.received: dict[str, list] = {}
        self.log_times: dict[str, list[int]] = {}
        self.error: BaseException | None = None
        self.finished = threading.Event()

    async def _run(self, done, timeout: float) -> None:
        async with websockets.connect(self.url, subprotocols=[SUBPROTOCOL],
                                      max_size=None) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            subs, classes = {}, {}
            deadline = time.monotonic() + timeout
            while not done(self.received) and time.monotonic() < deadline:
                try:
                    left = max(0.05, deadline - time.monotonic())
                    frame = await asyncio.wait_for(ws.recv(), left)
                except (asyncio.TimeoutError, websockets.ConnectionClosed):
                    break
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg["op"] == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            self.channels[ch["topic"]] = ch
                            sid = len(subs) + 1
                            subs[sid] = ch["topic"]
                            classes[ch["topic"]] = message_class(ch)
                            new.append({"id": sid, "channelId": ch["id"]})
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    continue
                assert frame[0] == MESSAGE_DATA
                sid, log_time = struct.unpack_from("<IQ", frame, 1)
                topic = subs[sid]
                self.received.setdefault(topic, []).append(classes[topic].FromString(frame[13:]))
                self.log_times.setdefault(topic, []).append(log_time)

    def start(self, done, timeout: float = 60.0) -> "FoxgloveClient":
        def target():
            try:
                asyncio.run(self._run(done, timeout))
            except BaseException as e:  # noqa: BLE001 - re-raised in the test thread
                self.error = e
            finally:
                self.finished.set()
        threading.Thread(target=target, daemon=True).start()
        return self

    def join(self, timeout: float = 90.0) -> "FoxgloveClient":
        assert self.finished.wait(timeout), "client did not finish"
        if self.error is not None:
            raise self.error
        return self


def every_topic(topics, n: int = 1):
    return lambda got: all(len(got.get(t, ())) >= n for t in topics)


def read_url(stream, pattern: str, timeout: float = 60.0) -> str:
    """The ws:// URL from the first line of a child's output matching ``pattern``; the output
    is drained on in a thread so the child never blocks on a full pipe."""
    found: list[str] = []
    lines: list[str] = []
    seen = threading.Event()

    def reader():
        for line in stream:
            lines.append(line)
            m = re.search(pattern, line)
            if m and not found:
                found.append(m.group(1))
                seen.set()
        seen.set()
    threading.Thread(target=reader, daemon=True).start()
    seen.wait(timeout)
    assert found, f"no server URL in the output: {''.join(lines)[-2000:]}"
    return found[0]


# ---------------------------------------------------------------------------------------------
# geometry of the scene messages
# ---------------------------------------------------------------------------------------------
def test_transforms_place_each_camera_at_its_centre_looking_along_its_axis():
    rig = two_camera_rig()
    tf = decode(scene.rig_transforms(5, rig_transforms(rig)))
    from scipy.spatial.transform import Rotation
    for t, cam in zip(tf.transforms, rig):
        assert (t.parent_frame_id, t.child_frame_id) == ("world", cam.name)
        pos = np.array([t.translation.x, t.translation.y, t.translation.z])
        np.testing.assert_allclose(pos, cam.center, atol=1e-9)
        R_wc = Rotation.from_quat([t.rotation.x, t.rotation.y, t.rotation.z,
                                   t.rotation.w]).as_matrix()
        # a point 5 m in front of the camera (camera frame) lands where the rig says
        X_cam = np.array([0.3, -0.2, 5.0])
        X_world = R_wc @ X_cam + pos
        np.testing.assert_allclose(cam.world_to_camera(X_world), X_cam, atol=1e-9)


def test_frustum_corners_project_to_the_image_corners():
    cam = two_camera_rig()[0]
    corners_cam = scene.frustum_corners(cam, 2.0)
    np.testing.assert_allclose(corners_cam[:, 2], 2.0)
    uv = (corners_cam / corners_cam[:, 2:]) @ cam.K.T
    np.testing.assert_allclose(uv[:, :2], [[0, 0], [cam.width, 0], [cam.width, cam.height],
                                           [0, cam.height]], atol=1e-9)


def test_skeletons_update_replaces_previous_frame_and_skips_missing_joints():
    _, ids, joints = known_frames()[1]  # track 3 lost joint 4 in this frame
    upd = decode(scene.skeletons_update(T0_NS, ids, joints, SPORTCENTER_13.bones))
    assert [d.type for d in upd.deletions] == [scene.SceneEntityDeletionType.All.value]
    by_id = {e.id: e for e in upd.entities}
    assert set(by_id) == {"person/3", "person/7", "untracked/2"}
    e3 = by_id["person/3"]
    assert len(e3.spheres) == 12
    assert [t.text for t in e3.texts] == ["3"] and not by_id["untracked/2"].texts
    n_bones = sum(4 not in b for b in SPORTCENTER_13.bones)
    assert len(e3.lines[0].points) == 2 * n_bones
    assert e3.spheres[0].color.r != by_id["person/7"].spheres[0].color.r or \
        e3.spheres[0].color.g != by_id["person/7"].spheres[0].color.g


def test_world_frame_name_is_configurable():
    rig = two_camera_rig()
    _, ids, joints = known_frames()[0]
    upd = decode(scene.skeletons_update(T0_NS, ids, joints, SPORTCENTER_13.bones,
                                        frame_id="court"))
    assert {e.frame_id for e in upd.entities} == {"court"}
    tf = decode(scene.rig_transforms(T0_NS, rig_transforms(rig, "court")))
    assert {t.parent_frame_id for t in tf.transforms} == {"court"}
    court = [e for e in decode(scene.rig_update(T0_NS, rig, world="court")).entities
             if e.id == "court"]
    assert court[0].frame_id == "court"


def test_untracked_id_is_the_wire_one():
    assert scene.UNTRACKED_ID == wire.UNTRACKED_ID


def test_annotations_are_the_rig_projection():
    cam = two_camera_rig()[1]
    _, ids, joints = known_frames()[0]
    ann = decode(scene.skeleton_annotations(T0_NS, cam, ids, joints, SPORTCENTER_13.bones))
    pts = [p for p in ann.points if p.type == scene.PointsAnnotationType.Points.value]
    assert len(pts) == 3
    want = cam.project(joints[0])
    got = np.array([[p.x, p.y] for p in pts[0].points])
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert sorted(t.text for t in ann.texts) == ["3", "7"]


# ---------------------------------------------------------------------------------------------
# bag source
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def image_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("fox") / "bag"
    known = write_poses_bag(path, known_frames(), images=True)
    return path, known


def watch_bags(bags, done) -> FoxgloveClient:
    """`maem-foxglove --bag ... --loop` on a free port, watched by a client until ``done``;
    the server must then stop cleanly on SIGTERM."""
    cmd = [str(BIN / "maem-foxglove"), "--port", "0", "--loop", "--rate", "3"]
    for b in bags:
        cmd += ["--bag", str(b)]
    with killed_on_exit(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         text=True)) as proc:
        url = read_url(proc.stdout, r"Foxglove server on (ws://\S+)")
        client = FoxgloveClient(url).start(done).join()
        proc.terminate()
        assert proc.wait(20) == 0
    return client


def _decoded_frames(known):
    return {s: (ids, j.astype(np.float32).astype(np.float64)) for s, ids, j in known.frames}


@pytest.mark.slow
def test_bag_source_channels_and_messages(image_bag):
    bag, known = image_bag
    cams = known.rig.names
    want = expected_schemas(cams)
    client = watch_bags([bag], every_topic(want, 2))
    assert {t: c["schemaName"] for t, c in client.channels.items()} == want
    got = client.received
    frames = _decoded_frames(known)
    # 3D skeletons: sphere centres are the bag's joints at the message's stamp
    for upd in got["/maem/skeletons"]:
        ent = {e.id: e for e in upd.entities}
        stamp = ent["person/3"].timestamp.seconds * 10**9 + ent["person/3"].timestamp.nanos
        ids, joints = frames[stamp]
        assert set(ent) == {f"person/{i}" for i in ids if i != wire.UNTRACKED_ID} | {
            f"untracked/{r}" for r, i in enumerate(ids) if i == wire.UNTRACKED_ID}
        for r, pid in enumerate(ids):
            if pid == wire.UNTRACKED_ID:
                continue
            centres = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z]
                                for s in ent[f"person/{pid}"].spheres])
            finite = np.isfinite(joints[r]).all(axis=1)
            np.testing.assert_allclose(centres, joints[r][finite], atol=1e-9)
    # the rig: court + one frustum per camera; transforms at the camera centres
    rig_ids = {e.id for e in got["/maem/rig"][0].entities}
    assert rig_ids == {"court"} | {f"camera/{c}" for c in cams}
    tf = {t.child_frame_id: t for t in got["/tf"][0].transforms}
    for cam in known.rig:
        np.testing.assert_allclose([tf[cam.name].translation.x, tf[cam.name].translation.y,
                                    tf[cam.name].translation.z], cam.center, atol=1e-9)
        # images: the bag's JPEGs, decodable, with the calibration's size
        img = got[f"/{cam.name}/image_raw/compressed"][0]
        assert img.format == "jpeg" and img.frame_id == cam.name
        bgr = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR)
        assert bgr.shape == (cam.height, cam.width, 3)
        calib = got[f"/{cam.name}/camera_info"][0]
        assert (calib.width, calib.height, calib.distortion_model) == (
            cam.width, cam.height, "plumb_bob")
        np.testing.assert_allclose(list(calib.K), cam.K.ravel())
        np.testing.assert_allclose(list(calib.D), cam.D)
        # 2D skeletons: the rig's projection of the bag's joints
        ann = got[f"/{cam.name}/skeletons_2d"][0]
        stamp = ann.points[0].timestamp.seconds * 10**9 + ann.points[0].timestamp.nanos
        ids, joints = frames[stamp]
        pts = [p for p in ann.points if p.type == scene.PointsAnnotationType.Points.value]
        proj = cam.project(joints[0])
        np.testing.assert_allclose([[q.x, q.y] for q in pts[0].points],
                                   proj[np.isfinite(proj).all(axis=1)], atol=1e-6)
    # log times are the recording's stamps
    assert set(client.log_times["/maem/skeletons"]) <= set(frames)


@pytest.mark.slow
def test_two_bags_merged_images_from_one_poses_from_the_other(tmp_path):
    """As after `make demo`: the camera bag (rig, images) plus a recorder bag (poses only)."""
    frames = known_frames(num_frames=3, dropped=())
    known = write_poses_bag(tmp_path / "cams", frames, images=True, topic="/other")
    write_poses_bag(tmp_path / "record", frames, store_rig=False)
    cam = known.rig.names[0]
    topics = ["/maem/skeletons", f"/{cam}/image_raw/compressed", f"/{cam}/skeletons_2d"]
    client = watch_bags([tmp_path / "record", tmp_path / "cams"], every_topic(topics, 3))
    stamps = {s for s, _, _ in frames}
    for t in topics:
        assert set(client.log_times[t]) <= stamps and len(client.received[t]) >= 3


@pytest.mark.parametrize("args, needle", [
    (["--bag", "/nonexistent/bag"], "not a rosbag2 folder"),
    (["--rate", "0"], "--rate: 0.0 must be > 0"),
    (["--rig", "no_such_rig"], "--rig 'no_such_rig'"),
    (["--topic", "/camera_0/camera_info"], "expected sensor_msgs/msg/PointCloud2"),
])
def test_bag_source_bad_inputs_exit_2(image_bag, args, needle):
    bag, _ = image_bag
    cmd = [str(BIN / "maem-foxglove"), "--port", "0"] + (
        [] if "--bag" in args else ["--bag", str(bag)]) + args
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr


@pytest.mark.slow
def test_bad_message_is_skipped_and_the_replay_goes_on(tmp_path):
    write_poses_bag(tmp_path / "bag", known_frames(num_frames=4, dropped=()), images=True,
                    malformed=(1,))
    res = subprocess.run([str(BIN / "maem-foxglove"), "--bag", str(tmp_path / "bag"), "--port",
                          "0", "--no-wait", "--rate", "4"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    skips = [ln for ln in res.stdout.splitlines() if ln.startswith("skipped /maem/poses")]
    assert len(skips) == 1 and "missing field" in skips[0], res.stdout
    # 4 poses - 1 malformed + 2 cameras x 4 x (image, camera_info)
    assert "sent 19 messages, skipped 1" in res.stdout, res.stdout


def test_port_in_use_exit_2(image_bag):
    from maem_ros.viz.bridge import FoxgloveBridge
    bag, known = image_bag
    taken = FoxgloveBridge(known.rig, port=0)
    port = taken.port
    try:
        res = subprocess.run([str(BIN / "maem-foxglove"), "--bag", str(bag), "--port",
                              str(port), "--no-wait"], capture_output=True, text=True,
                             timeout=60)
    finally:
        taken.close()
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and f"--port {port}: cannot listen" in res.stderr, res.stderr


@pytest.mark.slow
def test_help_lists_bag_options_and_node_parameters():
    res = subprocess.run([str(BIN / "maem-foxglove"), "--help"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0
    for needle in ("--bag", "--loop", "--rate", "--port", "image_transport (str, default",
                   "rig (str, default ''"):
        assert needle in res.stdout, needle


@pytest.mark.slow
def test_bag_without_rig_needs_rig_option(tmp_path):
    write_poses_bag(tmp_path / "norig", known_frames(num_frames=2, dropped=()), store_rig=False)
    res = subprocess.run([str(BIN / "maem-foxglove"), "--bag", str(tmp_path / "norig")],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "no rig in metadata" in res.stderr and "--rig" in res.stderr


# ---------------------------------------------------------------------------------------------
# live graph source: the node, fed by a test publisher
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("transport", ["compressed", "raw"])
@pytest.mark.ros
def test_live_node_serves_graph_topics(tmp_path, transport):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

    from maem_ros.ros.qos import IMAGE_QOS

    from helpers_ros import RELIABLE, ros_node, wait_for

    rig = two_camera_rig()
    rig_path = tmp_path / "rig.yaml"
    rig.to_yaml(rig_path)
    frames = known_frames(num_frames=4, dropped=())
    cmd = [str(BIN / "maem-foxglove"), "--ros-args", "-p", f"rig:={rig_path}", "-p", "port:=0",
           "-p", "static_period:=0.2", "-p", "diagnostics_period:=0.2",
           "-p", f"image_transport:={transport}"]
    # the raw variant also runs in a namespace: its inputs follow it (relative names)
    ns = "/team" if transport == "raw" else ""
    if ns:
        cmd += ["-r", f"__ns:={ns}"]
    env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM="0")
    want = expected_schemas(rig.names)
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             env=env)
    with killed_on_exit(child) as proc, ros_node("fox_test") as (node, ex):
        url = read_url(proc.stdout, r"Foxglove server on (ws://[0-9.]+:[0-9]+)")
        pose_pub = node.create_publisher(PointCloud2, f"{ns}/maem/poses", RELIABLE)
        raw = transport == "raw"
        suffix = "" if raw else "/compressed"
        img_pubs = {c: node.create_publisher(Image if raw else CompressedImage,
                                             f"{ns}/{c}/image_raw{suffix}", IMAGE_QOS)
                    for c in rig.names}
        info_pubs = {c: node.create_publisher(CameraInfo, f"{ns}/{c}/camera_info", IMAGE_QOS)
                     for c in rig.names}
        assert wait_for(lambda: pose_pub.get_subscription_count() > 0 and all(
            p.get_subscription_count() > 0 for p in [*img_pubs.values(), *info_pubs.values()]),
            30, ex)
        client = FoxgloveClient(url).start(every_topic(want, 1), timeout=60)
        frames_bgr = {c.name: np.full((c.height, c.width, 3), 60, np.uint8) for c in rig}
        jpgs = {c: cv2.imencode(".jpg", f)[1].tobytes() for c, f in frames_bgr.items()}
        k = 0

        def publish_round() -> bool:
            nonlocal k
            stamp, ids, joints = frames[k % len(frames)]
            stamp += (k // len(frames)) * len(frames) * 33_333_333
            pose_pub.publish(wire.poses_to_msg(stamp, "world", ids, joints, np.full(len(ids), 2),
                                               np.full(len(ids), 0.9)))
            for cam in rig:
                img_pubs[cam.name].publish(
                    wire.bgr_to_image(frames_bgr[cam.name], stamp, cam.name) if raw else
                    CompressedImage(header=wire.make_header(stamp, cam.name), format="jpeg",
                                    data=jpgs[cam.name]))
                info = cam.to_camera_info()
                info_pubs[cam.name].publish(CameraInfo(
                    header=wire.make_header(stamp, cam.name), width=info["width"],
                    height=info["height"], distortion_model=info["distortion_model"],
                    d=info["d"], k=info["k"], r=info["r"], p=info["p"]))
            k += 1
            return client.finished.is_set()

        assert wait_for(publish_round, 90, ex, step=0.05)
        client.join()
        # a malformed poses message is dropped with its reason in /diagnostics, the node goes on
        diag: dict[str, str] = {}
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diag.update(
            {kv.key: kv.value for st in m.status if st.name == f"{ns}/foxglove"
             for kv in st.values}),
            RELIABLE)
        bad = PointCloud2(header=wire.make_header(T0_NS, "world"))
        assert wait_for(lambda: pose_pub.publish(bad) or diag.get("dropped/missing_field")
                        not in (None, "0"), 30, ex, step=0.2)
        before = int(diag["frames_processed"])
        assert wait_for(lambda: (publish_round(), int(diag["frames_processed"]) > before)[1],
                        30, ex, step=0.2), diag
        assert proc.poll() is None
        proc.send_signal(2)
        assert proc.wait(20) == 0
    assert {t: c["schemaName"] for t, c in client.channels.items()} == want
    upd = client.received["/maem/skeletons"][0]
    assert {e.id for e in upd.entities} >= {"person/3", "person/7"}
    calib = client.received[f"/{rig[0].name}/camera_info"][-1]
    np.testing.assert_allclose(list(calib.K), rig[0].K.ravel())
    for cam in rig:
        img = client.received[f"/{cam.name}/image_raw/compressed"][0]
        assert img.format == "jpeg"
        if not raw:
            assert bytes(img.data) == jpgs[cam.name]
        bgr = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR)
        assert bgr.shape == (cam.height, cam.width, 3)
        assert abs(float(bgr.mean()) - 60) < 2


@pytest.mark.ros
def test_live_node_bad_rig_exits_2():
    res = subprocess.run([str(BIN / "maem-foxglove"), "--ros-args", "-p", "rig:=/no/such/rig"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "parameter 'rig'" in res.stderr


@pytest.mark.ros
def test_live_node_sends_rig_without_data_under_sim_time(tmp_path):
    """Court, frustums, transforms and calibrations reach a client with no data flowing, even
    with use_sim_time and no /clock (the resend timer runs on a steady clock)."""
    rig = two_camera_rig()
    rig.to_yaml(tmp_path / "rig.yaml")
    cmd = [str(BIN / "maem-foxglove"), "--ros-args", "-p", f"rig:={tmp_path / 'rig.yaml'}",
           "-p", "port:=0", "-p", "static_period:=0.2", "-p", "use_sim_time:=true"]
    env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM="0")
    topics = ["/maem/rig", "/tf"] + [f"/{c}/camera_info" for c in rig.names]
    with killed_on_exit(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         text=True, env=env)) as proc:
        url = read_url(proc.stdout, r"Foxglove server on (ws://[0-9.]+:[0-9]+)")
        client = FoxgloveClient(url).start(every_topic(topics, 2), timeout=30).join()
        proc.send_signal(2)
        assert proc.wait(20) == 0
    assert all(len(client.received.get(t, ())) >= 2 for t in topics), {
        t: len(v) for t, v in client.received.items()}
    assert "/maem/skeletons" not in client.received
