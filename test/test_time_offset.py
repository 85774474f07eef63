"""Per-camera time offsets: rig files (YAML, MAEM JSON, Pose2Sim TOML) and their application by
the synchroniser (core/sync.py) and the offline pipeline (scene folders, maem-eval)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from maem_ros.core.geometry.rig_formats import write_pose2sim_toml
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.interchange import MissingDataError, SceneFolder
from maem_ros.core.sync import ApproximateTimeSync, capture_stamp_ns, match_capture_times
from maem_ros.sim.rigs import build_rig

MS = 1_000_000
T0 = 1_700_000_000_000_000_000
PERIOD = 33_333_333


def _offset_rig() -> Rig:
    cams = build_rig("humanm3_3").cameras
    cams[1].time_offset = 0.0415
    cams[2].time_offset = -0.0123
    return Rig(cams)


@pytest.mark.parametrize("fmt", ["yaml", "json", "toml"])
def test_rig_with_offsets_round_trips(tmp_path, fmt):
    rig = _offset_rig()
    if fmt == "yaml":
        rig.to_yaml(tmp_path / "rig.yaml")
        back = Rig.load(tmp_path / "rig.yaml")
    elif fmt == "json":
        rig.to_json_folder(tmp_path / "cams")
        back = Rig.load(tmp_path / "cams")
    else:
        write_pose2sim_toml(tmp_path / "Calib.toml", rig.cameras)
        back = Rig.load(tmp_path / "Calib.toml")
    assert back.names == rig.names
    assert [c.time_offset for c in back] == [0.0, 0.0415, -0.0123]


def test_rig_without_the_key_reads_as_zero(tmp_path):
    rig = build_rig("humanm3_3")
    rig.to_yaml(tmp_path / "rig.yaml")
    assert "time_offset" not in (tmp_path / "rig.yaml").read_text()  # 0 is not written
    rig.to_json_folder(tmp_path / "cams")
    assert "time_offset" not in json.loads((tmp_path / "cams" / "camera_0.json").read_text())
    write_pose2sim_toml(tmp_path / "Calib.toml", rig.cameras)
    for path in (tmp_path / "rig.yaml", tmp_path / "cams", tmp_path / "Calib.toml"):
        assert [c.time_offset for c in Rig.load(path)] == [0.0] * 3


def test_qualisys_cameras_have_no_offset(tmp_path):
    from test_calibration import _CAM01, _CAM03, _qca  # the module's real-number fixtures
    assert [c.time_offset for c in Rig.load(_qca(tmp_path, _CAM01.format(rot=0), _CAM03))] \
        == [0.0, 0.0]


def test_bad_time_offset_names_the_camera(tmp_path):
    data = {"cameras": {"cam_a": build_rig("humanm3_3")[0].to_dict()}}
    data["cameras"]["cam_a"]["time_offset"] = "soon"
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="camera 'cam_a' time_offset: 'soon' is not a number"):
        Rig.load(tmp_path / "rig.yaml")
    with pytest.raises(ValueError, match="camera 'x' time_offset: nan is not finite"):
        Camera("x", np.eye(3), np.eye(3), np.zeros(3), 10, 10, time_offset=float("nan"))


def test_capture_stamp_adds_the_offset():
    assert capture_stamp_ns(T0, 0.0415) == T0 + 41_500_000
    assert capture_stamp_ns(T0, -0.0123) == T0 - 12_300_000
    np.testing.assert_array_equal(capture_stamp_ns(np.array([0, 10]), 1e-9), [1, 11])


def test_sync_pairs_messages_of_an_offset_camera():
    """cam1's stamps run 45 ms early (offset +45 ms, more than the 20 ms slop): by raw stamp it
    would pair each frame with the wrong one of cam0; by capture time it pairs correctly."""
    sync = ApproximateTimeSync(["cam0", "cam1"], slop_ns=20 * MS, max_wait_ns=150 * MS,
                               time_offsets={"cam1": 0.045})
    out = []
    for k in range(6):
        now = T0 + k * PERIOD + 5 * MS
        capture = T0 + k * PERIOD
        out += sync.add("cam0", capture, ("cam0", k), now_ns=now)
        out += sync.add("cam1", capture - 45 * MS, ("cam1", k), now_ns=now)
    out += sync.poll(T0 + 10 * PERIOD)
    full = [fs for fs in out if not fs.missing]
    assert len(full) == 6
    for fs in full:
        assert fs.items["cam0"][1] == fs.items["cam1"][1]
        assert fs.stamp_ns == T0 + fs.items["cam0"][1] * PERIOD  # capture time, not the raw stamp
    assert not sync.lagging()  # the offset is no transport lag

    unaware = ApproximateTimeSync(["cam0", "cam1"], slop_ns=20 * MS, max_wait_ns=150 * MS)
    wrong = []
    for k in range(6):
        now = T0 + k * PERIOD + 5 * MS
        wrong += unaware.add("cam0", T0 + k * PERIOD, ("cam0", k), now_ns=now)
        wrong += unaware.add("cam1", T0 + k * PERIOD - 45 * MS, ("cam1", k), now_ns=now)
    wrong += unaware.poll(T0 + 10 * PERIOD)
    assert any(fs.items["cam0"][1] != fs.items["cam1"][1] for fs in wrong
               if len(fs.items) == 2)


def test_sync_rejects_offsets_of_unknown_cameras():
    with pytest.raises(ValueError, match="time_offsets: unknown camera"):
        ApproximateTimeSync(["a", "b"], 1, 2, time_offsets={"c": 0.1})


def test_match_capture_times_nearest_within_tolerance():
    stamps = [T0 + k * PERIOD for k in range(10)]
    ref = [T0 + 3 * PERIOD, T0 + 9 * PERIOD + 20 * MS]
    # stamps run 40 ms late (offset -40 ms): frame k is captured at k * PERIOD - 40 ms
    idx = match_capture_times(ref, stamps, -0.040, PERIOD // 2)
    assert idx.tolist() == [4, -1]  # 4*33.3-40 = 93.3 ms, nearest to 100 ms; 9*: none near
    assert match_capture_times(ref, [], 0.0, PERIOD).tolist() == [-1, -1]


def test_scene_folder_matches_frames_by_capture_time(tmp_path):
    """An offline frame set of a scene whose camera_1 has stamps 50 ms late takes camera_1's
    frame captured nearest (frame - 2 at 30 fps) and stamps it with its capture time."""
    from maem_ros.sim.scene import Scene
    scene = Scene({"rig": "humanm3_3", "frames": 8, "difficulty": "none", "players": 2,
                   "bystanders": 0, "num_vertices": 60})
    rig = _offset_rig()
    rig[1].time_offset = -0.050
    folder = SceneFolder.create(tmp_path, rig, {"fps": 30.0, "start_stamp_ns": scene.stamp_ns(0)})
    for f in range(8):
        for cam in rig.names:
            folder.write_outputs(cam, f, scene.raw_outputs(cam, f))
    assert folder.capture_frame("camera_0", 5) == 5
    assert folder.capture_frame("camera_1", 5) == 7  # 7 * 33.3 ms - 50 ms = 183 ms ~ 5 * 33.3
    dets = folder.detections_at("camera_1", 5)
    assert dets.stamp_ns == scene.stamp_ns(7) - 50 * MS
    assert folder.capture_frame("camera_1", 7) is None  # no later frame
    with pytest.raises(MissingDataError, match="no frame captured near frame 7"):
        folder.detections_at("camera_1", 7)


def test_sim_camera_with_an_offset_samples_the_motion_at_its_own_time(tmp_path):
    """A camera offset by exactly one frame period sees at frame k what it sees at frame k+1
    of the same scene without offsets; the other cameras are unchanged; the rig carries it."""
    from maem_ros.sim.scene import Scene
    base = {"rig": "humanm3_3", "frames": 6, "difficulty": "none", "players": 3, "bystanders": 0,
            "num_vertices": 60}
    plain = Scene(base)
    shifted = Scene({**base, "time_offsets": {"camera_1": 1 / 30}})
    assert [c.time_offset for c in shifted.rig] == [0.0, 1 / 30, 0.0]
    def by_person(scene, cam, k):  # detection order is shuffled per camera and frame
        order = np.argsort(scene.detection_persons(cam, k))
        return scene.detections(cam, k).kpts2d[order]

    for k in range(5):
        np.testing.assert_array_equal(by_person(shifted, "camera_1", k),
                                      by_person(plain, "camera_1", k + 1))
        np.testing.assert_array_equal(by_person(shifted, "camera_0", k),
                                      by_person(plain, "camera_0", k))
        np.testing.assert_array_equal(shifted.gt_keypoints(k), plain.gt_keypoints(k))
    # a half-frame offset lies between the neighbouring frames
    half = Scene({**base, "time_offsets": {"camera_1": -0.5 / 30}})
    mid = half.skeleton(half.capture_position("camera_1", 3)).points
    a, b = plain.skeleton(2).points, plain.skeleton(3).points
    assert np.abs(mid - (a + b) / 2).max() < 0.5 * np.abs(b - a).max() + 1e-3
    with pytest.raises(ValueError, match="unknown camera"):
        Scene({**base, "time_offsets": {"camera_7": 0.01}})
    with pytest.raises(ValueError, match="time_offsets"):
        Scene({**base, "time_offsets": {"camera_1": 2.0}})


@pytest.mark.slow
def test_maem_sim_time_offsets_and_intrinsics_only(tmp_path):
    import subprocess
    import sys
    out = tmp_path / "scene"
    done = subprocess.run([str(Path(sys.executable).parent / "maem-sim"), str(out), "--rig",
                           "humanm3_3", "--frames", "3", "--vertices", "60", "--quiet",
                           "--time-offset", "camera_2=-0.025", "--intrinsics-only"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    truth = Rig.load(out / "gt_rig.yaml")
    assert [c.time_offset for c in truth] == [0.0, 0.0, -0.025]
    for name in truth.names:
        assert "extrinsic_r" not in json.loads((out / "cameras" / f"{name}.json").read_text())
    with pytest.raises(ValueError, match="intrinsics only: calibrate the rig first"):
        Rig.load(out)
    intr = Rig.load_intrinsics(out)
    for t, c in zip(truth, intr):
        np.testing.assert_array_equal(c.K, t.K)
        assert (c.width, c.height, c.time_offset) == (t.width, t.height, t.time_offset)
        np.testing.assert_array_equal(c.R, np.eye(3))  # a placeholder, not the truth
    info = json.loads((out / "scene.json").read_text())
    assert info["scene_config"]["time_offsets"] == {"camera_2": -0.025}
    bad = subprocess.run([str(Path(sys.executable).parent / "maem-sim"), str(tmp_path / "x"),
                          "--time-offset", "camera_2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "expected CAMERA=SECONDS" in bad.stderr


@pytest.mark.slow
def test_maem_eval_applies_the_rig_offsets(tmp_path):
    """A scene whose camera_1 captures 2 frames late: maem-eval with the rig's time_offset
    pairs its frames by capture time (as good as a synchronised scene); the same scene with the
    offset erased from the rig pairs wrong frames and loses accuracy."""
    from maem_ros.tools.eval.evaluate import build_parser, evaluate_scene
    from maem_ros.tools.simulate import write_scene
    from maem_ros.sim.scene import SceneConfig
    base = dict(rig="humanm3_3", frames=14, difficulty="easy", players=4, bystanders=0,
                num_vertices=400, seed=3)
    write_scene(tmp_path / "sync", SceneConfig(**base), progress=False)
    write_scene(tmp_path / "late", SceneConfig(**base, time_offsets={"camera_1": 2 / 30}),
                progress=False)
    import shutil
    shutil.copytree(tmp_path / "late", tmp_path / "erased")
    cams = tmp_path / "erased" / "cameras" / "camera_1.json"
    data = json.loads(cams.read_text())
    del data["time_offset"]
    cams.write_text(json.dumps(data))
    reports = {}
    for name in ("sync", "late", "erased"):
        args = build_parser().parse_args([str(tmp_path / name), "--params", "humanm3.yaml",
                                          "--frames", "12", "--quiet", "--temporal", "off"])
        reports[name] = evaluate_scene(args, log=lambda *a: None)
    # GT frame f takes camera_1's frame f - 2; frames 0, 1 have none: skipped, named
    assert reports["late"]["skips"]["missing_npz"] == 2
    # frames 2.. (all three views): MPJPE mm
    mpjpe = {name: float(np.nanmean(r["per_frame_mpjpe"][2:])) for name, r in reports.items()}
    assert mpjpe["late"] < mpjpe["sync"] + 5.0, mpjpe
    assert mpjpe["erased"] > mpjpe["late"] + 30.0, mpjpe
