"""core/geometry/camera.py (geometry, rig I/O), core/detections.py validation, params.py loading."""
from __future__ import annotations

import json
import shutil
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from helpers_scene import CALIB, random_detections

from maem_ros.core.geometry.camera import Camera, Rig, fundamental_matrix
from maem_ros.core.detections import FrameDetections
from maem_ros.params import load_node_params

#: distortion coefficients per model (plumb_bob: the real SportCenter camera's)
DISTORTIONS = {
    "plumb_bob": [-0.34599753537794525, 0.12371631805378626, -0.0067956570218813935,
                  -0.0006137302991591332, -0.012496602996881016],
    "rational_polynomial": [0.12, -0.05, 0.001, -0.0008, 0.01, 0.08, -0.03, 0.004],
    "equidistant": [0.05, -0.012, 0.003, -0.0006],
}
#: largest normalised image radius (fisheye: ray angle; cv2.fisheye clamps distorted angles
#: beyond pi/2, so near-90 degree rays do not invert) tested per model
MAX_RADIUS = {"plumb_bob": 0.8, "rational_polynomial": 0.9, "equidistant": 1.3}  # theta, rad


def make_camera(model: str = "plumb_bob", name: str = "cam", seed: int = 0,
                K_rect: np.ndarray | None = None) -> Camera:
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.uniform(-5, 5, 3)
    K = [[820.0, 0.0, 690.0], [0.0, 835.0, 500.0], [0.0, 0.0, 1.0]]
    return Camera(name, K=K, R=R, t=t, width=1376, height=992, distortion_model=model,
                  D=DISTORTIONS[model], K_rect=K_rect)


def points_in_view(cam: Camera, xn: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points whose normalised camera coordinates are xn (N,2) at depth (N,)."""
    Xc = np.concatenate([xn * depth[:, None], depth[:, None]], axis=1)
    return (Xc - cam.t) @ cam.R  # inverse of X_c = R X + t


def assert_cameras_equal(a: Camera, b: Camera, atol: float = 1e-12) -> None:
    assert (a.name, a.width, a.height, a.distortion_model) == (b.name, b.width, b.height, b.distortion_model)
    for f in ("K", "R", "t", "D", "K_rect"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), atol=atol, err_msg=f)


# ------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("model", sorted(DISTORTIONS))
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_project_undistort_round_trip(model: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    cam = make_camera(model, seed=seed % 1000)
    r = MAX_RADIUS[model] * np.sqrt(rng.uniform(0, 1, 64))
    a = rng.uniform(0, 2 * np.pi, 64)
    xn = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    if model == "equidistant":  # fisheye: r is the ray angle theta; tan keeps it a pinhole coordinate
        xn = xn / np.maximum(r, 1e-12)[:, None] * np.tan(r)[:, None]
    X = points_in_view(cam, xn, rng.uniform(2, 40, 64))
    raw = cam.project(X)
    rect = cam.project_rectified(X)
    assert np.all(np.isfinite(raw))
    assert np.abs(cam.undistort_points(raw) - rect).max() < 0.01
    assert np.abs(cam.distort_points(rect) - raw).max() < 0.01
    # the distortion is real: raw and rectified differ somewhere
    assert np.abs(raw - rect).max() > 1.0


def test_rectified_intrinsics_differ_from_raw() -> None:
    K_rect = np.array([[600.0, 0, 700], [0, 600.0, 480], [0, 0, 1]])
    cam = make_camera("plumb_bob", K_rect=K_rect)
    X = points_in_view(cam, np.array([[0.1, -0.2], [0.3, 0.25]]), np.array([5.0, 12.0]))
    np.testing.assert_allclose(cam.undistort_points(cam.project(X)), cam.project_rectified(X), atol=0.01)
    h = (cam.P @ np.c_[X, np.ones(2)].T).T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], cam.project_rectified(X), atol=1e-9)


def test_points_behind_camera_are_nan() -> None:
    cam = make_camera("plumb_bob")
    X = points_in_view(cam, np.array([[0.1, 0.1], [0.1, 0.1]]), np.array([-3.0, 3.0]))
    assert np.isnan(cam.project(X)[0]).all() and np.isfinite(cam.project(X)[1]).all()
    assert np.isnan(cam.project_rectified(X)[0]).all()


def looking_at_origin(name: str, centre: np.ndarray, model: str = "plumb_bob") -> Camera:
    z = -centre / np.linalg.norm(centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return Camera(name, K=[[820.0, 0, 690], [0, 835.0, 500], [0, 0, 1]], R=R, t=-R @ centre,
                  width=1376, height=992, distortion_model=model, D=DISTORTIONS[model])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_fundamental_matrix_epipolar_constraint(seed: int) -> None:
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(2, 3)) * [1, 1, 0.2] + [0, 0, 0.5]
    centres = 12.0 * centres / np.linalg.norm(centres, axis=1, keepdims=True)
    a, b = looking_at_origin("a", centres[0]), looking_at_origin("b", centres[1])
    X = rng.normal(scale=2.0, size=(50, 3))
    ua, ub = a.project_rectified(X), b.project_rectified(X)
    assert np.isfinite(ua).all() and np.isfinite(ub).all()
    F = fundamental_matrix(a, b)
    xa, xb = np.c_[ua, np.ones(50)], np.c_[ub, np.ones(50)]
    lines = xa @ F.T  # epipolar lines in b
    dist = np.abs((xb * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert dist.max() < 1e-6  # px
    np.testing.assert_allclose(np.linalg.norm(F), 1.0)
    assert abs(np.linalg.det(F)) < 1e-12
    # the wrong direction (x_a^T F x_b) does not vanish in general: the test can fail
    swapped = np.abs((xa * (xb @ F.T)).sum(1)) / np.linalg.norm((xb @ F.T)[:, :2], axis=1)
    assert swapped.max() > 1e-3


def test_rig_fundamental_matrices_keys_and_direction() -> None:
    rig = Rig([make_camera("plumb_bob", f"c{k}", seed=k) for k in range(3)])
    Fs = rig.fundamental_matrices()
    assert sorted(Fs) == [(0, 1), (0, 2), (1, 2)]
    np.testing.assert_allclose(Fs[(0, 2)], fundamental_matrix(rig[0], rig[2]))


# ----------------------------------------------------------------------------------- rig I/O
@pytest.fixture()
def real_rig_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "cams"
    folder.mkdir()
    shutil.copy(CALIB / "sportcenter_fisheye_param_00.json", folder / "camera_10.json")
    shutil.copy(CALIB / "humanm3_camera_0.json", folder / "camera_2.json")
    return folder


def test_real_maem_jsons(real_rig_folder: Path) -> None:
    rig = Rig.load(real_rig_folder)
    assert rig.names == ["camera_2", "camera_10"]  # natural order, named by file stem
    hm3, sc = rig["camera_2"], rig["camera_10"]
    # Human-M3: 4x4 extrinsic, 3x4 intrinsic, no distortion keys, no size
    assert hm3.distortion_model == "plumb_bob" and not hm3.has_distortion
    np.testing.assert_allclose(hm3.K, [[1204.6082, 0, 1022.172], [0, 1204.79912, 779.553157], [0, 0, 1]])
    np.testing.assert_allclose(hm3.t, [-4.280879020690918, 0.2078360617160797, 35.26551055908203])
    assert (hm3.width, hm3.height) == (2044, 1559)  # twice the principal point
    assert np.linalg.norm(hm3.center) == pytest.approx(35.5, abs=0.5)
    # SportCenter: extrinsic_r + extrinsic_t, OpenCV 5 coefficients, explicit size
    assert sc.distortion_model == "plumb_bob" and sc.D.shape == (5,)
    np.testing.assert_allclose(sc.D, DISTORTIONS["plumb_bob"])
    assert (sc.width, sc.height) == (1376, 992)
    assert np.linalg.norm(sc.center) == pytest.approx(15.5, abs=0.2)
    # the world origin (court centre) is in front of both cameras and inside the image
    for cam in rig:
        uv = cam.project(np.zeros((1, 3)))[0]
        assert 0 <= uv[0] < cam.width and 0 <= uv[1] < cam.height
    sized = Rig.from_json_folder(real_rig_folder, default_size=(2048, 1536))
    assert (sized["camera_2"].width, sized["camera_2"].height) == (2048, 1536)
    assert sized["camera_10"].width == 1376


def test_rig_yaml_round_trip(tmp_path: Path, real_rig_folder: Path) -> None:
    cams = [make_camera(m, f"cam_{m}", seed=k) for k, m in enumerate(sorted(DISTORTIONS))]
    K_rect = np.array([[500.0, 0, 600], [0, 500.0, 400], [0, 0, 1]])
    cams.append(make_camera("plumb_bob", "rect", seed=9, K_rect=K_rect))
    rig = Rig(cams + Rig.load(real_rig_folder).cameras)
    rig.to_yaml(tmp_path / "rig.yaml")
    back = Rig.load(tmp_path / "rig.yaml")
    assert back.names == rig.names
    for a, b in zip(rig, back):
        assert_cameras_equal(a, b)


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
def test_camera_info_round_trip(model: str) -> None:
    cam = make_camera(model, K_rect=np.array([[700.0, 0, 680], [0, 700.0, 490], [0, 0, 1]]))
    info = cam.to_camera_info()
    assert info["distortion_model"] == model and len(info["d"]) == len(DISTORTIONS[model])
    assert len(info["k"]) == 9 and len(info["p"]) == 12 and len(info["r"]) == 9
    json.dumps(info)  # plain types only
    assert_cameras_equal(Camera.from_camera_info(cam.name, info, cam.R, cam.t), cam)


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
def test_maem_json_round_trip(model: str, tmp_path: Path) -> None:
    cam = make_camera(model, name="camera_0")
    data = json.loads(json.dumps(cam.to_maem_json()))
    assert_cameras_equal(Camera.from_maem_json(data), cam)
    rig = Rig([cam, make_camera(model, name="camera_1", seed=3)])
    rig.to_json_folder(tmp_path)
    back = Rig.load(tmp_path)
    for a, b in zip(rig, back):
        assert_cameras_equal(a, b)


def test_maem_json_extrinsic_forms_agree() -> None:
    cam = make_camera("plumb_bob")
    d = cam.to_maem_json()
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = cam.R, cam.t
    d4 = {k: v for k, v in d.items() if k not in ("extrinsic_r", "extrinsic_t")}
    d4["extrinsic"] = E.tolist()
    d4["intrinsic"] = np.c_[cam.K, np.zeros(3)].tolist()  # 3x4 form
    assert_cameras_equal(Camera.from_maem_json(d4, name="cam"), cam)
    # camera->world extrinsics flagged with world2cam: false are inverted
    inv = dict(d, extrinsic_r=cam.R.T.tolist(), extrinsic_t=(-cam.R.T @ cam.t).tolist(), world2cam=False)
    assert_cameras_equal(Camera.from_maem_json(inv, name="cam"), cam, atol=1e-9)


# --------------------------------------------------------------------------------- bad input
def _camera_kwargs(**over) -> dict:
    kw = dict(name="bad", K=np.eye(3), R=np.eye(3), t=np.zeros(3), width=640, height=480)
    kw.update(over)
    return kw


@pytest.mark.parametrize("over,field", [
    ({"K": [[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]]}, "K"),
    ({"K": np.eye(4)}, "K"),
    ({"t": [0.0, np.inf, 0.0]}, "t"),
    ({"distortion_model": "kannala"}, "distortion_model"),
    ({"R": np.diag([1.0, 1.0, -1.0])}, "R"),
    ({"R": [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}, "R"),  # det 1, sheared
    ({"R": 2.0 * np.eye(3)}, "R"),
    ({"D": [0.1, 0.0, 0.0, 0.0, 0.0, 0.3]}, "D"),
    ({"D": [np.nan, 0, 0, 0, 0]}, "D"),
    ({"width": 0}, "size"),
])
def test_bad_camera_names_field(over: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        Camera(**_camera_kwargs(**over))


def test_bad_maem_json_and_rig_files(tmp_path: Path) -> None:
    good = make_camera("plumb_bob").to_maem_json()
    with pytest.raises(ValueError, match="intrinsic"):
        Camera.from_maem_json({k: v for k, v in good.items() if k != "intrinsic"})
    with pytest.raises(ValueError, match="extrinsic"):
        Camera.from_maem_json({k: v for k, v in good.items() if not k.startswith("extrinsic")})
    with pytest.raises(ValueError, match="distortion_type"):
        Camera.from_maem_json({**{k: v for k, v in good.items() if k != "distortion_model"},
                               "distortion_type": "omni"})
    with pytest.raises(ValueError, match="no such file"):
        Rig.load(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="no camera JSON"):
        Rig.load(tmp_path)
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(ValueError, match="unreadable JSON"):
        Rig.load(tmp_path)
    (tmp_path / "rig.yaml").write_text("cameras: []\n")
    with pytest.raises(ValueError, match="cameras"):
        Rig.load(tmp_path / "rig.yaml")
    (tmp_path / "rig2.yaml").write_text("cameras: {a: {width: 10, height: 10, K: [1]}}\n")
    with pytest.raises(ValueError, match="missing R, t"):
        Rig.load(tmp_path / "rig2.yaml")
    with pytest.raises(ValueError, match="duplicate"):
        Rig([make_camera(name="x"), make_camera(name="x", seed=1)])
    rig = Rig([make_camera(name="x")])
    with pytest.raises(ValueError, match="unknown camera 'y'"):
        rig["y"]
    with pytest.raises(ValueError, match="unknown camera 'y'"):
        rig.index("y")


# ------------------------------------------------------------------------------- detections
#: two random detections (4 keypoints, 3 vertices) in fixed boxes; FrameDetections fields
#: given per call replace the drawn ones (the bad-input cases)
detections = partial(random_detections, 2, 4, 3, stamp_ns=5, score=0.9, kpts=(0.0, 100.0),
                     verts=(0.0, 100.0), bboxes=np.tile([10.0, 20.0, 110.0, 220.0], (2, 1)))


def test_valid_detections_and_helpers() -> None:
    d = detections().validate(known_cameras=["cam0", "cam1"])
    assert (d.n, d.num_joints, d.num_vertices) == (2, 4, 3)
    np.testing.assert_allclose(d.centers, [[60.0, 120.0]] * 2)
    assert d.verts2d.dtype == np.float32
    assert d.select(np.array([True, False])).n == 1
    empty = FrameDetections.empty("cam0", 1, 70, 0).validate()
    assert (empty.n, empty.num_joints) == (0, 70)


def _with(arr_name: str, fn) -> FrameDetections:
    d = detections()
    setattr(d, arr_name, fn(getattr(d, arr_name).copy()))
    return d


def _set(a: np.ndarray, index, value) -> np.ndarray:
    a[index] = value
    return a


@pytest.mark.parametrize("make,field", [
    (lambda: detections(bboxes=np.zeros((2, 3))), "bbox"),
    (lambda: detections(scores=np.ones(3)), "score"),
    (lambda: detections(kpts2d=np.zeros((2, 4, 3))), "kpts2d"),
    (lambda: detections(kpts3d=np.zeros((2, 5, 3))), "kpts3d"),
    (lambda: detections(verts2d=np.zeros((1, 3, 2))), "verts2d"),
    (lambda: _with("kpts2d", lambda a: _set(a, (1, 2, 0), np.inf)), "kpts2d"),  # NaN = not seen
    (lambda: _with("kpts3d", lambda a: _set(a, (0, 0, 2), np.inf)), "kpts3d"),
    (lambda: _with("verts2d", lambda a: _set(a, (1, 0, 1), np.inf)), "verts2d"),  # NaN = missing
    (lambda: _with("bboxes", lambda a: _set(a, (0, 0), np.inf)), "bbox"),
    (lambda: _with("scores", lambda a: _set(a, 1, np.nan)), "score"),
    (lambda: _with("scores", lambda a: _set(a, 1, 1.5)), "score"),
    (lambda: _with("bboxes", lambda a: _set(a, 1, [50.0, 20.0, 40.0, 220.0])), "inverted"),
    (lambda: _with("bboxes", lambda a: _set(a, 0, [10.0, 300.0, 110.0, 220.0])), "inverted"),
])
def test_bad_detections_name_field(make, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        make().validate()


def test_nan_reports_detection_index() -> None:
    with pytest.raises(ValueError, match="kpts2d: inf in detection 1"):
        _with("kpts2d", lambda a: _set(a, (1, 2, 0), np.inf)).validate()
    with pytest.raises(ValueError, match="kpts3d: NaN or inf in detection 1"):
        _with("kpts3d", lambda a: _set(a, (1, 2, 0), np.nan)).validate()


def test_keypoint_not_seen_is_nan() -> None:
    d = _with("kpts2d", lambda a: _set(a, (1, 2, 0), np.nan))
    assert d.validate() is d


def test_unknown_camera() -> None:
    with pytest.raises(ValueError, match="camera: unknown camera 'cam9'"):
        detections(camera="cam9").validate(known_cameras=["cam0", "cam1"])


# ------------------------------------------------------------------------------------ params
def test_load_node_params_merges_global_section(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text(
        "/**:\n  ros__parameters:\n    rig: r1\n    tau_det: 0.5\n"
        "association:\n  ros__parameters:\n    tau_det: 0.9\n    k_min: 4\n"
        "/triangulation:\n  ros__parameters:\n    tau_kps: 20.0\n")
    assert load_node_params(f, "association") == {"rig": "r1", "tau_det": 0.9, "k_min": 4}
    assert load_node_params(f, "triangulation") == {"rig": "r1", "tau_det": 0.5, "tau_kps": 20.0}
    assert load_node_params(f, "frontend") == {"rig": "r1", "tau_det": 0.5}


def test_load_node_params_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("association:\n  tau_det: 0.9\n")  # no ros__parameters
    with pytest.raises(ValueError, match="ros__parameters"):
        load_node_params(bad, "association")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ValueError, match="mapping"):
        load_node_params(tmp_path / "list.yaml", "association")
    (tmp_path / "broken.yaml").write_text("a: [1\n")
    with pytest.raises(ValueError, match="unreadable"):
        load_node_params(tmp_path / "broken.yaml", "association")
    with pytest.raises(ValueError, match="not a file"):
        load_node_params(tmp_path / "nope.yaml", "association")


@pytest.mark.parametrize("name,tau_det,k_min", [("sportcenter.yaml", 0.9, 4), ("humanm3.yaml", 0.7, 2)])
def test_shipped_params_files(name: str, tau_det: float, k_min: int) -> None:
    p = load_node_params(name, "association")
    assert p["tau_det"] == tau_det and p["k_min"] == k_min and "rig" in p
    assert load_node_params(name, "triangulation")["tau_kps"] == 20.0


@pytest.mark.parametrize("K", [np.zeros((3, 3)), [[800, 0, 640], [0, 800, 360], [0, 0, 2]],
                               [[-800, 0, 640], [0, 800, 360], [0, 0, 1]],
                               [[800, 0, 640], [5, 800, 360], [0, 0, 1]]])
def test_non_pinhole_intrinsics_rejected(K):
    with pytest.raises(ValueError, match="camera 'c' K: not pinhole intrinsics"):
        Camera("c", K, np.eye(3), [0, 0, 5], 1280, 720)


def test_nan_vertices_are_missing_not_invalid() -> None:
    """A vertex the compact wire layout cannot carry arrives as NaN: valid, it takes no part in
    the epipolar gate (core.association.gates.epipolar)."""
    assert _with("verts2d", lambda a: _set(a, (1, 0, 1), np.nan)).validate() is not None
