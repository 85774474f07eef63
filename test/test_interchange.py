"""MAEM interchange: npz / GT / camera JSON round trips, raw-vs-rectified px, corrupt input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers_scene import sportcenter_camera

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.detections import FrameDetections
from maem_ros.core.interchange import (MissingDataError, SceneFolder, detections_to_outputs,
                                       outputs_to_detections, read_gt, read_maem_npz, validate_output,
                                       write_gt, write_maem_npz)


def fisheye_camera(name: str = "fish") -> Camera:
    pb = sportcenter_camera()
    return Camera(name, pb.K, pb.R, pb.t, pb.width, pb.height, "equidistant", [-0.03, 0.01, -0.004, 0.0006])


CAMERAS = {"plumb_bob": sportcenter_camera, "equidistant": fisheye_camera}


def make_outputs(n: int = 2, j: int = 70, v: int = 40, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        x1, y1 = rng.uniform(100, 600, 2)
        out.append({
            "bbox": np.array([x1, y1, x1 + 60, y1 + 180], np.float32),
            "bbox_score": np.float32(0.5 + 0.4 * rng.random()),
            "pred_keypoints_3d": rng.normal(0, 0.4, (j, 3)).astype(np.float32),
            "pred_keypoints_2d": rng.uniform(100, 800, (j, 2)).astype(np.float32),
            "pred_keypoints_2d_verts": rng.uniform(100, 800, (v, 2)).astype(np.float32),
            "pred_cam_t": np.array([0.1 * i, 0.2, 12.0], np.float32),
            "focal_length": np.float32(830.0),
        })
    return out


# ---- npz --------------------------------------------------------------------------------------
def test_npz_round_trip(tmp_path):
    outputs = make_outputs()
    path = tmp_path / "000000.npz"
    write_maem_npz(path, outputs)
    back = read_maem_npz(path)
    assert len(back) == 2
    for a, b in zip(outputs, back):
        assert set(a) == set(b)
        for k in a:
            np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))


def test_npz_authors_layout_plain_savez(tmp_path):
    # the authors call np.savez(path, outputs=list_of_dicts); both an (N,) and a 0-d object array load
    path = tmp_path / "a.npz"
    np.savez(path, outputs=make_outputs(3))
    assert len(read_maem_npz(path)) == 3
    zero_d = np.empty((), dtype=object)
    zero_d[()] = make_outputs(1)[0]
    np.savez(tmp_path / "b.npz", outputs=zero_d)
    assert len(read_maem_npz(tmp_path / "b.npz")) == 1
    np.savez(tmp_path / "c.npz", outputs=np.zeros(0))
    assert read_maem_npz(tmp_path / "c.npz") == []


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.pop("bbox_score"), "bbox_score"),
    (lambda d: d.update(pred_keypoints_2d=np.zeros((70, 3))), "pred_keypoints_2d"),
    (lambda d: d.update(pred_keypoints_2d=np.zeros((69, 2))), "pred_keypoints_2d"),
    (lambda d: d.update(pred_keypoints_3d=np.full((70, 3), np.nan)), "pred_keypoints_3d"),
    (lambda d: d.update(pred_keypoints_2d_verts=np.array([[np.inf, 0.0]])), "pred_keypoints_2d_verts"),
    (lambda d: d.update(bbox=np.array([10.0, 10.0, 5.0, 20.0])), "bbox"),
    (lambda d: d.update(bbox=np.zeros(3)), "bbox"),
    (lambda d: d.update(bbox_score=1.5), "bbox_score"),
    (lambda d: d.update(pred_cam_t="far"), "pred_cam_t"),
])
def test_npz_bad_dict_names_file_and_field(tmp_path, mutate, field):
    outputs = make_outputs(2)
    mutate(outputs[1])
    path = tmp_path / "000007.npz"
    arr = np.empty(2, dtype=object)
    arr[0], arr[1] = outputs
    np.savez(path, outputs=arr)
    with pytest.raises(ValueError) as e:
        read_maem_npz(path)
    msg = str(e.value)
    assert "000007.npz" in msg and field in msg and "outputs[1]" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("content", [b"", b"not a zip at all", b"PK\x03\x04garbage-truncated"])
def test_npz_corrupt_file(tmp_path, content):
    path = tmp_path / "bad.npz"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="bad.npz"):
        read_maem_npz(path)


def test_npz_wrong_arrays(tmp_path):
    np.savez(tmp_path / "no_outputs.npz", boxes=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="no 'outputs'"):
        read_maem_npz(tmp_path / "no_outputs.npz")
    np.savez(tmp_path / "numeric.npz", outputs=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="object array"):
        read_maem_npz(tmp_path / "numeric.npz")
    arr = np.empty(1, dtype=object)
    arr[0] = [1, 2, 3]
    np.savez(tmp_path / "list.npz", outputs=arr)
    with pytest.raises(ValueError, match="expected a dict"):
        read_maem_npz(tmp_path / "list.npz")
    with pytest.raises(MissingDataError):
        read_maem_npz(tmp_path / "absent.npz")


_values = st.one_of(
    st.none(), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3),
    st.builds(lambda s: np.zeros(s), st.tuples(st.integers(0, 4), st.integers(0, 4))),
    st.builds(lambda s, v: np.full(s, v), st.tuples(st.integers(1, 72)), st.floats(allow_nan=True)),
    st.lists(st.floats(-1e3, 1e3), max_size=5))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(["bbox", "bbox_score", "pred_keypoints_3d", "pred_keypoints_2d",
                                        "pred_keypoints_2d_verts", "pred_cam_t", "junk"]), _values))
def test_validate_output_fuzz_only_valueerror(d):
    good = make_outputs(1, j=4, v=3)[0]
    merged = {**good, **d}
    try:
        out = validate_output(merged, "fuzz")
    except ValueError as e:
        assert str(e).startswith("fuzz")
        return
    assert out["pred_keypoints_2d"].shape[0] == out["pred_keypoints_3d"].shape[0]
    assert np.all(np.isfinite(out["pred_keypoints_2d_verts"]))


# ---- raw vs rectified --------------------------------------------------------------------------
def world_points_in_view(cam: Camera, n: int, seed: int = 0) -> np.ndarray:
    """(n,3) world points whose raw projection is inside the image (5 % margin), 4-30 m away."""
    rng = np.random.default_rng(seed)
    raw = rng.uniform([0.05 * cam.width, 0.05 * cam.height], [0.95 * cam.width, 0.95 * cam.height], (n, 2))
    rect = cam.undistort_points(raw)
    rays = np.concatenate([(rect - cam.K_rect[:2, 2]) / np.diag(cam.K_rect)[:2], np.ones((n, 1))], axis=1)
    Xc = rays * rng.uniform(4, 30, (n, 1))
    return (Xc - cam.t) @ cam.R


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_outputs_to_detections_undistorts_against_projection(model):
    cam = CAMERAS[model]()
    assert cam.distortion_model == model and cam.has_distortion
    people, j, v = 3, 70, 500
    X = world_points_in_view(cam, people * (j + v), seed=1).reshape(people, j + v, 3)
    raw, rect = cam.project(X), cam.project_rectified(X)
    assert np.max(np.abs(raw - rect)) > 5.0  # the distortion is strong enough to matter
    outputs = []
    for i in range(people):
        lo, hi = raw[i].min(0), raw[i].max(0)
        outputs.append({"bbox": np.concatenate([lo, hi]), "bbox_score": 0.95,
                        "pred_keypoints_3d": cam.world_to_camera(X[i, :j]), "pred_keypoints_2d": raw[i, :j],
                        "pred_keypoints_2d_verts": raw[i, j:]})
    dets = outputs_to_detections(outputs, cam, 123)
    dets.validate([cam.name])
    assert (dets.camera, dets.stamp_ns, dets.n, dets.num_joints, dets.num_vertices) == (cam.name, 123, 3, j, v)
    assert np.max(np.abs(dets.kpts2d - rect[:, :j])) < 0.01
    assert np.max(np.abs(dets.verts2d - rect[:, j:])) < 0.01
    raw_box = np.stack([o["bbox"] for o in outputs])
    np.testing.assert_allclose(dets.bboxes[:, 2:] - dets.bboxes[:, :2], raw_box[:, 2:] - raw_box[:, :2])
    want_centre = cam.undistort_points(0.5 * (raw_box[:, :2] + raw_box[:, 2:]))
    assert np.max(np.abs(dets.centers - want_centre)) < 1e-6
    np.testing.assert_allclose(dets.kpts3d, cam.world_to_camera(X[:, :j]), atol=1e-9)


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_detections_outputs_round_trip_through_file(tmp_path, model):
    cam = CAMERAS[model]()
    X = world_points_in_view(cam, 2 * 80, seed=2).reshape(2, 80, 3)
    rect = cam.project_rectified(X)
    lo, hi = rect.min(1), rect.max(1)
    dets = FrameDetections(cam.name, 5, np.concatenate([lo, hi], 1), np.array([0.91, 0.6]),
                           rect[:, :70], cam.world_to_camera(X[:, :70]), rect[:, 70:])
    outputs = detections_to_outputs(dets, cam)
    assert np.max(np.abs(outputs[0]["pred_keypoints_2d"] - cam.project(X[0, :70]))) < 0.01
    write_maem_npz(tmp_path / "f.npz", outputs)
    back = outputs_to_detections(read_maem_npz(tmp_path / "f.npz"), cam, 5)
    for field in ("bboxes", "kpts2d", "verts2d"):
        assert np.max(np.abs(getattr(back, field) - getattr(dets, field))) < 0.01, field
    np.testing.assert_allclose(back.scores, dets.scores, atol=1e-6)
    np.testing.assert_allclose(back.kpts3d, dets.kpts3d, atol=1e-5)


def test_outputs_to_detections_empty_and_inconsistent():
    cam = sportcenter_camera()
    empty = outputs_to_detections([], cam, 7)
    assert empty.n == 0 and empty.num_joints == 70 and empty.stamp_ns == 7
    outputs = make_outputs(2, v=40)
    outputs[1]["pred_keypoints_2d_verts"] = np.zeros((41, 2))
    with pytest.raises(ValueError, match=r"outputs\[1\].*vertices"):
        outputs_to_detections(outputs, cam, 0)


# ---- ground truth --------------------------------------------------------------------------------
def test_gt_round_trip_with_masked_joints(tmp_path):
    rng = np.random.default_rng(3)
    pose = rng.normal(0, 3, (4, 3, 13, 3))
    mask = np.ones((4, 3, 13), bool)
    mask[1, 2] = False          # person absent in frame 1
    mask[2, 0, [5, 6]] = False  # two joints not annotated
    pose[1, 2] = np.nan
    write_gt(tmp_path / "gt.npz", pose, mask, "sportcenter_13")
    with np.load(tmp_path / "gt.npz") as z:
        assert z["pose"].shape == (4, 3, 13, 4)
        assert np.all(z["pose"][..., 3][mask] == 1.0)
    got, got_mask, conv = read_gt(tmp_path / "gt.npz")
    assert conv == "sportcenter_13" and got.shape == (4, 3, 13, 4)
    np.testing.assert_array_equal(got_mask, mask)
    np.testing.assert_allclose(got[..., :3][mask], pose[mask])
    assert np.all(np.isnan(got[..., :3][~mask]))


def test_gt_xrmocap_keypoints_key_and_errors(tmp_path):
    kp = np.zeros((2, 1, 13, 4))
    kp[..., 3] = 1
    np.savez(tmp_path / "x.npz", keypoints=kp, mask=np.ones((2, 1, 13)), convention="sportcenter_13")
    assert read_gt(tmp_path / "x.npz")[0].shape == (2, 1, 13, 4)
    np.savez(tmp_path / "m.npz", pose=kp, mask=np.ones((2, 1, 12)))
    with pytest.raises(ValueError, match="mask"):
        read_gt(tmp_path / "m.npz")
    kp[0, 0, 4, 0] = np.nan
    np.savez(tmp_path / "n.npz", pose=kp, mask=np.ones((2, 1, 13)))
    with pytest.raises(ValueError, match="frame 0 person 0 joint 4"):
        read_gt(tmp_path / "n.npz")
    with pytest.raises(ValueError, match="NaN"):
        write_gt(tmp_path / "w.npz", kp[..., :3], np.ones((2, 1, 13), bool), "sportcenter_13")
    (tmp_path / "c.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="unreadable"):
        read_gt(tmp_path / "c.npz")


# ---- scene folders -------------------------------------------------------------------------------
def test_scene_folder_round_trip(tmp_path):
    rig = Rig([sportcenter_camera("cam_a"), fisheye_camera("cam_b"), fisheye_camera("cam_c")])
    folder = SceneFolder.create(tmp_path / "s", rig, {"fps": 25.0, "start_stamp_ns": 1000})
    back = SceneFolder(tmp_path / "s")
    assert back.views == ["cam_a", "cam_b", "cam_c"]
    for a, b in zip(rig, back.rig):
        assert a.distortion_model == b.distortion_model
        for f in ("K", "R", "t", "D"):
            np.testing.assert_allclose(getattr(a, f), getattr(b, f), err_msg=f)
    folder.write_outputs("cam_a", 0, make_outputs(2))
    folder.write_outputs("cam_a", 2, make_outputs(1))
    folder.write_outputs("cam_b", 2, [])
    (tmp_path / "s" / "dets" / "stray").mkdir()
    back = SceneFolder(tmp_path / "s")
    assert back.num_frames == 3 and back.unknown_det_views() == ["stray"]
    assert back.stamp_ns(2) == 1000 + 80_000_000 and back.frame_at(1000 + 81_000_000) == 2
    assert back.frame_at(1000 - 30_000_000) is None and back.frame_at(1000 - 10_000_000) == 0
    dets = back.detections("cam_a", 0)
    assert dets.n == 2 and dets.stamp_ns == 1000
    assert back.detections("cam_b", 2).n == 0
    with pytest.raises(MissingDataError, match="frame 1"):
        back.detections("cam_a", 1)
    with pytest.raises(MissingDataError, match="no dets/cam_c/"):
        back.detections("cam_c", 0)
    with pytest.raises(MissingDataError):
        back.gt()


def test_scene_folder_needs_cameras(tmp_path):
    with pytest.raises(ValueError, match="no such folder"):
        SceneFolder(tmp_path / "nope")
    with pytest.raises(ValueError, match="cameras/"):
        SceneFolder(tmp_path)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**62), st.floats(1.0, 240.0), st.integers(0, 10**6), st.floats(-0.49, 0.49))
def test_frame_stamp_round_trip(start, fps, frame, jitter):
    from maem_ros.core.interchange import frame_at_stamp, frame_stamp_ns
    stamp = frame_stamp_ns(frame, start, fps)
    assert frame_at_stamp(stamp + int(jitter * 1e9 / fps), start, fps) == frame
    assert frame_at_stamp(start - int(0.6e9 / fps), start, fps) is None
