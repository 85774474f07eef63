"""maem-make-bag: build bags from a small generated frames folder / scene folder and read them
back with rosbags and, independently, with the mcap package's ROS 2 decoder."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.interchange import (SceneFolder, outputs_to_detections, read_maem_npz,
                                       write_gt, write_maem_npz)
from maem_ros.ros.wire import TF_STATIC_TOPIC, msg_to_detections, msg_to_poses, msg_to_transforms
from maem_ros import bagio
from maem_ros.tools.bags.make_bag import main, stamp_ns

FPS = 10.0
START = 1_700_000_000_000_000_000
NFRAMES = 4
J, V = 70, 40


def make_rig() -> Rig:
    K = [[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]
    R_b = cv2.Rodrigues(np.array([0.0, 0.2, 0.0]))[0]
    return Rig([Camera("cam_a", K, np.eye(3), [0, 0, 5], 64, 48, "plumb_bob", [0.02, -0.01, 0, 0, 0]),
                Camera("cam_b", K, R_b, [1, 0, 5], 64, 48, "equidistant", [0.01, 0.002, 0, 0])])


def fake_outputs(rng: np.random.Generator, n: int) -> list[dict]:
    return [dict(bbox=np.array([10.0, 8, 30, 40]), bbox_score=np.float32(0.95),
                 pred_keypoints_3d=rng.normal(size=(J, 3)),
                 pred_keypoints_2d=rng.uniform(5, 45, size=(J, 2)),
                 pred_keypoints_2d_verts=rng.uniform(5, 45, size=(V, 2)),
                 pred_cam_t=np.array([0.0, 0, 5])) for _ in range(n)]


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    """frames/<cam>/<k>.jpg|png (cam_a jpeg, cam_b png), dets/<cam>/<k>.npz, gt.npz, rig.yaml."""
    rng = np.random.default_rng(0)
    rig = make_rig()
    rig.to_yaml(tmp_path / "rig.yaml")
    for cam, ext in (("cam_a", ".jpg"), ("cam_b", ".png")):
        (tmp_path / "frames" / cam).mkdir(parents=True)
        for k in range(NFRAMES):
            img = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
            assert cv2.imwrite(str(tmp_path / "frames" / cam / f"{k:06d}{ext}"), img)
            write_maem_npz(tmp_path / "dets" / cam / f"{k:06d}.npz", fake_outputs(rng, k % 3))
    pose = rng.uniform(-2, 2, size=(NFRAMES, 2, 13, 3))
    mask = np.ones((NFRAMES, 2, 13), bool)
    mask[1, 0, 3] = False
    mask[2, 1] = False  # person 1 absent in frame 2
    write_gt(tmp_path / "gt.npz", pose, mask, "sportcenter_13")
    return tmp_path


def build(dataset: Path, *extra: str) -> tuple[int, Path]:
    out = dataset / "bag"
    rc = main([str(out), "--frames-dir", str(dataset / "frames"), "--rig", str(dataset / "rig.yaml"),
               "--fps", str(FPS), "--dets", str(dataset / "dets"), "--gt", str(dataset / "gt.npz"),
               "--quiet", *extra])
    return rc, out


def assert_rig_transforms(transforms, rig: Rig) -> None:
    """world -> camera transforms that map each camera's optical-frame points to world."""
    assert [(t.parent, t.child) for t in transforms] == [("world", c) for c in rig.names]
    X = np.random.default_rng(5).uniform(-3, 3, (20, 3))
    for t in transforms:
        np.testing.assert_allclose(t.apply(rig[t.child].world_to_camera(X)), X, atol=1e-6)


def test_stamp_rounding_matches_scene_folder():
    assert stamp_ns(START, 30.0, 1) == START + 33_333_333
    assert stamp_ns(START, 30.0, 2) == START + 66_666_667


def test_bag_read_back_with_rosbags(dataset: Path):
    rc, out = build(dataset)
    assert rc == 0
    assert (out / "metadata.yaml").is_file() and (out / "bag.mcap").is_file()
    rig = make_rig()
    info = bagio.bag_info(out)
    expected = {f"/{c}/{t}": NFRAMES for c in rig.names
                for t in ("camera_info", "image_raw/compressed", "detections")}
    expected[bagio.GT_TOPIC] = NFRAMES
    assert info.counts == {**expected, TF_STATIC_TOPIC: 1}
    assert info.qos[TF_STATIC_TOPIC][0].durability == bagio.QosDurability.TRANSIENT_LOCAL
    assert info.topics["/cam_a/image_raw/compressed"] == bagio.COMPRESSED_IMAGE
    assert info.start_ns == START and info.end_ns == START + (NFRAMES - 1) * 100_000_000
    assert info.custom[bagio.CUSTOM_GT_CONVENTION] == "sportcenter_13"
    rig_back = _rig_from_text(bagio.read_rig_yaml(out), dataset)
    assert rig_back.names == rig.names
    np.testing.assert_allclose(rig_back["cam_b"].R, rig["cam_b"].R)

    seen = {t: [] for t in expected}
    for m in bagio.read_messages(out):
        msg = m.decode()
        if m.topic == TF_STATIC_TOPIC:
            assert m.log_time_ns == START
            assert_rig_transforms(msg_to_transforms(msg, m.topic), rig)
            continue
        k = (m.log_time_ns - START) // 100_000_000
        assert m.log_time_ns == START + k * 100_000_000
        assert bagio.stamp_to_ns(msg.header.stamp) == m.log_time_ns
        seen[m.topic].append(k)
        cam = m.topic.split("/")[1]
        if m.topic.endswith("camera_info"):
            ref = rig[cam].to_camera_info()
            assert msg.header.frame_id == cam
            assert (msg.width, msg.height, msg.distortion_model) == (64, 48, ref["distortion_model"])
            for key in "dkrp":
                np.testing.assert_array_equal(getattr(msg, key), ref[key])
        elif m.topic.endswith("compressed"):
            ext = ".jpg" if cam == "cam_a" else ".png"
            assert msg.format == ("jpeg" if cam == "cam_a" else "png")
            assert msg.data.tobytes() == (dataset / "frames" / cam / f"{k:06d}{ext}").read_bytes()
        elif m.topic.endswith("detections"):
            got = msg_to_detections(msg, m.topic, expected_camera=cam)
            ref = outputs_to_detections(read_maem_npz(dataset / "dets" / cam / f"{k:06d}.npz"),
                                        rig[cam], m.log_time_ns)
            assert got.n == k % 3 and got.stamp_ns == m.log_time_ns
            if got.n:
                assert got.num_joints == J and got.num_vertices == V
                np.testing.assert_allclose(got.kpts2d, ref.kpts2d, rtol=1e-6, atol=1e-4)
                np.testing.assert_allclose(got.verts2d, ref.verts2d, rtol=1e-6, atol=1e-4)
                np.testing.assert_allclose(got.bboxes, ref.bboxes, rtol=1e-6, atol=1e-4)
        else:
            poses = msg_to_poses(msg, m.topic)
            with np.load(dataset / "gt.npz") as z:
                pose, mask = z["pose"][k], z["mask"][k].astype(bool)
            present = np.flatnonzero(mask.any(axis=1))
            np.testing.assert_array_equal(poses.ids, present)
            ref = np.where(mask[present, :, None], pose[present, :, :3], np.nan)
            np.testing.assert_allclose(poses.joints, ref, rtol=1e-6, atol=1e-6)
    for t, ks in seen.items():
        assert ks == list(range(NFRAMES)), t


def _rig_from_text(text: str, tmp: Path) -> Rig:
    path = tmp / "rig_back.yaml"
    path.write_text(text)
    return Rig.from_yaml(path)


def test_bag_read_back_with_mcap_decoder(dataset: Path):
    rc, out = build(dataset)
    assert rc == 0
    rig = make_rig()
    counts: dict[str, int] = {}
    with open(out / "bag.mcap", "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert decoded
    for _schema, channel, m, msg in decoded:
        topic = channel.topic
        counts[topic] = counts.get(topic, 0) + 1
        if topic == TF_STATIC_TOPIC:  # decoded by mcap_ros2 from the schema rosbags wrote
            assert _schema.name == "tf2_msgs/msg/TFMessage" and m.log_time == START
            assert_rig_transforms(msg_to_transforms(msg, topic), rig)
            continue
        k = (m.log_time - START) // 100_000_000
        assert m.log_time == START + k * 100_000_000
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == m.log_time
        cam = topic.split("/")[1]
        if topic.endswith("camera_info"):
            ref = rig[cam].to_camera_info()
            assert msg.distortion_model == ref["distortion_model"]
            assert list(msg.k) == ref["k"] and list(msg.d) == ref["d"] and list(msg.p) == ref["p"]
        elif topic.endswith("compressed"):
            ext = ".jpg" if cam == "cam_a" else ".png"
            assert bytes(msg.data) == (dataset / "frames" / cam / f"{k:06d}{ext}").read_bytes()
        elif topic.endswith("detections"):
            assert msg.width == k % 3 and msg.header.frame_id == cam
            counts_f = {f.name: f.count for f in msg.fields}
            assert counts_f == {"bbox": 4, "score": 1, "kpts2d": 2 * J, "kpts3d": 3 * J,
                                "verts2d": 2 * V if msg.width else counts_f["verts2d"]}
            assert len(msg.data) == msg.width * msg.point_step
    assert counts == bagio.bag_info(out).counts


def test_bad_inputs_are_skipped_and_summarised(dataset: Path, capsys):
    (dataset / "frames" / "cam_b" / "000002.png").unlink()  # missing frame
    (dataset / "frames" / "cam_a" / "000003.jpg").write_bytes(b"not an image")
    (dataset / "frames" / "stray").mkdir()  # camera with no calibration
    cv2.imwrite(str(dataset / "frames" / "stray" / "000000.jpg"), np.zeros((8, 8, 3), np.uint8))
    rc, out = build(dataset)
    err = capsys.readouterr().err
    assert rc == 0
    assert "skipped 1 x missing image of camera cam_b: 000002" in err
    assert "skipped 1 x unreadable image" in err and "000003.jpg" in err
    assert "camera 'stray' has no calibration" in err
    counts = bagio.bag_info(out).counts
    assert counts["/cam_a/image_raw/compressed"] == NFRAMES - 1
    assert counts["/cam_b/image_raw/compressed"] == NFRAMES - 1
    assert "/stray/camera_info" not in counts


def test_nothing_writable_exits_nonzero(dataset: Path, capsys):
    rig = Rig([make_rig()["cam_a"]])
    rig.to_yaml(dataset / "only_a.yaml")
    frames = dataset / "other"
    (frames / "cam_z").mkdir(parents=True)
    cv2.imwrite(str(frames / "cam_z" / "0.png"), np.zeros((8, 8, 3), np.uint8))
    rc = main([str(dataset / "bag2"), "--frames-dir", str(frames), "--rig",
               str(dataset / "only_a.yaml"), "--fps", "5", "--quiet"])
    assert rc != 0
    assert "no <camera>/*.jpg|png folder matching" in capsys.readouterr().err
    assert main([str(dataset / "bag3"), "--frames-dir", str(dataset / "nope"), "--rig",
                 str(dataset / "rig.yaml"), "--fps", "5"]) == 2
    build(dataset)
    assert build(dataset)[0] == 2  # output exists: not overwritten


def test_scene_folder_and_vertex_subset(tmp_path: Path):
    rng = np.random.default_rng(1)
    rig = make_rig()
    scene_info = {"fps": 30.0, "start_stamp_ns": 1_234_000_000_000, "num_frames": 3,
                  "scene_config": {"rig": "test", "seed": 7, "difficulty": "none"}}
    folder = SceneFolder.create(tmp_path / "scene", rig, scene_info)
    for k in range(3):
        for cam in rig.names:
            folder.write_outputs(cam, k, fake_outputs(rng, 1))
        folder.write_image("cam_a", k, rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    folder.write_gt(rng.uniform(size=(3, 1, 13, 3)), np.ones((3, 1, 13), bool))
    out = tmp_path / "bag"
    assert main([str(out), "--scene", str(tmp_path / "scene"), "--max-vertices", "10",
                 "--compress", "--quiet"]) == 0
    info = bagio.bag_info(out)
    assert json.loads(info.custom[bagio.CUSTOM_SCENE]) == scene_info
    assert bagio.read_scene(out) == scene_info
    assert bagio.read_scene_config(out) == scene_info["scene_config"]
    assert info.counts["/cam_a/image_raw/compressed"] == 3
    assert "/cam_b/image_raw/compressed" not in info.counts  # cam_b has detections only
    assert info.counts["/cam_b/detections"] == 3 and info.counts[bagio.SCENE_TOPIC] == 1
    assert info.qos[bagio.SCENE_TOPIC][0].durability == bagio.QosDurability.TRANSIENT_LOCAL
    msgs = list(bagio.read_messages(out))
    assert msgs[0].topic == bagio.SCENE_TOPIC
    assert json.loads(msgs[0].decode().data) == scene_info
    for m in msgs:
        if m.topic.endswith("detections"):
            k = folder.frame_at(m.log_time_ns)
            assert m.log_time_ns == folder.stamp_ns(k)
            got = msg_to_detections(m.decode(), m.topic)
            full = folder.detections(got.camera, k)
            idx = np.unique(np.linspace(0, V - 1, 10).round().astype(int))
            assert got.num_vertices == len(idx) == 10
            np.testing.assert_allclose(got.verts2d, full.verts2d[:, idx], rtol=1e-6, atol=1e-4)
