"""Frontend backends: npz and synthetic return the right FrameDetections for a stamp."""
from __future__ import annotations

import numpy as np
import pytest

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.interchange import SceneFolder, detections_to_outputs
from maem_ros.core.detections import FrameDetections
from maem_ros.frontend.base import Estimator, StridedEstimator, backends, make_estimator, register_backend

START = 1_700_000_000_000_000_000
PERIOD = 1_000_000_000 // 25


def _rig() -> Rig:
    K = [[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]]
    R = np.diag([1.0, -1.0, -1.0])  # looking down at the floor from 10 m
    return Rig([Camera("cam_a", K, R, [0, 0, 10], 1280, 720, "plumb_bob", [-0.2, 0.05, 0.001, 0.0, 0.0]),
                Camera("cam_b", K, R, [1, 0, 10], 1280, 720, "equidistant", [0.02, -0.01, 0.0, 0.0])])


def _dets(cam: Camera, frame: int, n: int = 2, v: int = 30) -> FrameDetections:
    rng = np.random.default_rng(frame)
    kp = rng.uniform([300, 200], [900, 500], (n, 70, 2))
    verts = rng.uniform([300, 200], [900, 500], (n, v, 2))
    box = np.concatenate([verts.min(1), verts.max(1)], 1)
    return FrameDetections(cam.name, START + frame * PERIOD, box, rng.uniform(0.5, 1, n), kp,
                           rng.normal(0, 0.5, (n, 70, 3)) + [0, 0, 10], verts)


@pytest.fixture
def scene(tmp_path):
    rig = _rig()
    folder = SceneFolder.create(tmp_path / "scene", rig, {"fps": 25.0, "start_stamp_ns": START})
    for cam in rig:
        for f in range(3):
            folder.write_outputs(cam.name, f, detections_to_outputs(_dets(cam, f), cam))
    return folder


def test_npz_backend_returns_rectified_frame_for_stamp(scene):
    rig = scene.rig
    for root in (scene.root, scene.root / "dets"):  # scene root or its dets/
        est = make_estimator("npz", {"dets_dir": str(root), "backend": "npz"}, rig)
        assert not est.needs_image
        for cam in rig:
            stamp = START + 2 * PERIOD + 7_000_000  # jitter inside half a period
            got = est.estimate(cam, stamp, None).validate(rig.names)
            want = _dets(cam, 2)
            assert got.camera == cam.name and got.stamp_ns == stamp
            assert np.max(np.abs(got.kpts2d - want.kpts2d)) < 0.01
            assert np.max(np.abs(got.verts2d - want.verts2d)) < 0.01
            np.testing.assert_allclose(got.scores, want.scores, atol=1e-6)


def test_npz_backend_bad_stamps_and_files(scene):
    rig = scene.rig
    est = make_estimator("npz", {"dets_dir": str(scene.root)}, rig)
    with pytest.raises(ValueError, match="no frame"):
        est.estimate(rig["cam_a"], START - PERIOD, None)
    with pytest.raises(ValueError, match="frame 5"):
        est.estimate(rig["cam_a"], START + 5 * PERIOD, None)
    (scene.root / "dets" / "cam_a" / "000001.npz").write_bytes(b"corrupt")
    with pytest.raises(ValueError, match="000001.npz"):
        est.estimate(rig["cam_a"], START + PERIOD, None)
    # explicit options override scene.json: a 50 fps clock maps this stamp to frame 2
    fast = make_estimator("npz", {"dets_dir": str(scene.root), "fps": 50, "start_stamp_ns": START}, rig)
    assert fast.estimate(rig["cam_b"], START + PERIOD, None).n == 2
    with pytest.raises(ValueError, match="dets_dir"):
        make_estimator("npz", {}, rig)
    with pytest.raises(ValueError, match="'fps'"):
        make_estimator("npz", {"dets_dir": str(scene.root), "fps": -1}, rig)


def test_vertex_stride_and_registry(scene):
    rig = scene.rig
    est = make_estimator("npz", {"dets_dir": str(scene.root), "vertex_stride": 4}, rig)
    assert not isinstance(est, StridedEstimator)  # npz drops vertices before undistorting them
    full = make_estimator("npz", {"dets_dir": str(scene.root)}, rig).estimate(rig[0], START, None)
    got = est.estimate(rig[0], START, None)
    assert got.num_vertices == 8
    np.testing.assert_array_equal(got.verts2d, full.verts2d[:, ::4])
    np.testing.assert_array_equal(got.kpts2d, full.kpts2d)
    with pytest.raises(ValueError, match="vertex_stride"):
        make_estimator("npz", {"dets_dir": str(scene.root), "vertex_stride": 0}, rig)
    with pytest.raises(ValueError, match="unknown 'nope'"):
        make_estimator("nope", {}, rig)
    assert {"synthetic", "npz", "sam3d_body"} <= set(backends())

    class Fixed(Estimator):
        needs_image = True

        def __init__(self, options, rig):
            self.value = options["value"]

        def estimate(self, camera, stamp_ns, image):
            return FrameDetections.empty(camera.name, stamp_ns + self.value, 70, 0)

    register_backend("test_fixed", Fixed)
    est = make_estimator("test_fixed", {"value": 3}, rig)
    assert est.needs_image and est.estimate(rig[1], 10, np.zeros((2, 2, 3), np.uint8)).stamp_ns == 13
    # a backend that does not apply vertex_stride itself gets wrapped
    register_backend("test_verts", lambda options, rig: _Verts())
    wrapped = make_estimator("test_verts", {"vertex_stride": 3}, rig)
    assert isinstance(wrapped, StridedEstimator) and not wrapped.needs_image
    out = wrapped.estimate(rig[0], 0, None)
    np.testing.assert_array_equal(out.verts2d[0, :, 0], [0, 3, 6, 9])
    assert _Verts.last.num_vertices == 10  # the backend's own object is left untouched


class _Verts(Estimator):
    needs_image = False
    last = None

    def estimate(self, camera, stamp_ns, image):
        verts = np.stack([np.arange(10.0), np.zeros(10)], 1)[None]
        _Verts.last = FrameDetections(camera.name, stamp_ns, [[0, 0, 9, 1]], [0.9], np.zeros((1, 70, 2)),
                                      np.zeros((1, 70, 3)), verts)
        return _Verts.last




def test_synthetic_backend_matches_scene():
    from maem_ros.sim.scene import Scene, SceneConfig
    from maem_ros.frontend.synthetic import scene_config_dict
    cfg = SceneConfig(rig="humanm3_3", frames=4, seed=3, difficulty="easy", num_vertices=300)
    scene = Scene(cfg)
    options = {"scene_dict": cfg.to_dict(), "backend": "synthetic", "slop": 0.02}
    est = make_estimator("synthetic", options, scene.rig)
    assert not est.needs_image
    cam = scene.rig[1]
    stamp = scene.stamp_ns(2) + 3_000_000
    got, want = est.estimate(cam, stamp, None), scene.detections(cam.name, 2)
    assert got.camera == cam.name and got.stamp_ns == stamp and got.n == want.n
    for field in ("bboxes", "scores", "kpts2d", "kpts3d", "verts2d"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    with pytest.raises(ValueError, match="not a frame"):
        est.estimate(cam, scene.stamp_ns(0) - 10**9, None)
    # explicit keys override scene_dict; a JSON string (as stored in bags) works too
    import json
    d = scene_config_dict({"scene_dict": json.dumps({"scene_config": cfg.to_dict()}), "seed": 9})
    assert d["seed"] == 9 and d["rig"] == "humanm3_3"
    with pytest.raises(ValueError, match="scene_dict"):
        scene_config_dict({"scene_dict": "{not json"})


def test_npz_backend_reproduces_synthetic_backend(tmp_path):
    """maem-sim's npz files (RAW px, float32) decode to the simulator's own rectified detections."""
    from maem_ros.tools import simulate
    out = tmp_path / "sim"
    assert simulate.main([str(out), "--rig", "sportcenter6", "--frames", "2", "--difficulty", "medium",
                          "--seed", "1", "--vertices", "300", "--quiet"]) == 0
    folder = SceneFolder(out)
    rig = folder.rig
    synth = make_estimator("synthetic", {"scene_dict": folder.info["scene_config"]}, rig)
    npz = make_estimator("npz", {"dets_dir": str(out / "dets")}, rig)
    total = 0
    for cam in rig:
        for frame in range(2):
            stamp = folder.stamp_ns(frame)
            a, b = npz.estimate(cam, stamp, None), synth.estimate(cam, stamp, None)
            assert a.n == b.n and a.stamp_ns == b.stamp_ns == stamp
            total += a.n
            for field in ("bboxes", "kpts2d", "verts2d"):
                err = np.abs(getattr(a, field) - getattr(b, field))
                assert err.size == 0 or err.max() < 0.01, (cam.name, frame, field, err.max())
            np.testing.assert_allclose(a.kpts3d, b.kpts3d, atol=1e-5)
            np.testing.assert_allclose(a.scores, b.scores, atol=1e-6)
    assert total > 20


def test_option_int_keeps_nanosecond_stamps_exact():
    from maem_ros.frontend.base import option_int
    stamp = 1_700_000_000_123_456_789  # > 2^53: a float round trip would change it
    for value in (stamp, str(stamp), np.int64(stamp)):
        assert option_int({"s": value}, "s", 0) == stamp
    assert option_int({"s": 3.0}, "s", 0) == 3
    for bad in (3.5, True, "x", None):
        with pytest.raises(ValueError, match="'s': expected an integer"):
            option_int({"s": bad}, "s", 0)
