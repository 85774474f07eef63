"""maem-export: TRC / C3D / CSV read back (ezc3d, a TRC parser, csv) equal the bag's poses."""
from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import ezc3d
import numpy as np
import pytest

from helpers_bags import FPS, STEP_NS, T0_NS, known_frames, read_poses, write_poses_bag
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.ros import wire
from maem_ros.tools.export.export import main as export_main

REPO = Path(__file__).resolve().parent.parent
NAMES = SPORTCENTER_13.names
GT_TOPIC = "/maem/gt_poses"


def run_export(*args: str) -> subprocess.CompletedProcess:
    """The console script as a user runs it."""
    exe = Path(sys.executable).with_name("maem-export")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=120)


def parse_trc(path: Path) -> dict:
    """A TRC file (OpenSim / Pose2Sim layout) -> header fields, marker names, frames, times,
    (K, M, 3) coordinates with NaN for empty cells."""
    lines = path.read_text().split("\n")
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    header = dict(zip(keys, values))
    markers = [m for m in lines[3].split("\t")[2:] if m]
    sub = lines[4].split("\t")[2:]
    assert sub == [f"{a}{i}" for i in range(1, len(markers) + 1) for a in "XYZ"]
    assert lines[5] == ""
    rows = [ln.split("\t") for ln in lines[6:] if ln]
    for r in rows:
        assert len(r) == 3 + 3 * len(markers) and r[-1] == "", r  # trailing tab
        r.pop()
    frames = np.array([int(r[0]) for r in rows])
    times = np.array([float(r[1]) for r in rows])
    xyz = np.array([[float(c) if c else np.nan for c in r[2:]] for r in rows])
    return {"header": header, "markers": markers, "frames": frames, "times": times,
            "xyz": xyz.reshape(len(rows), len(markers), 3)}


def expected_grid(frames, track: int) -> np.ndarray:
    """(K, J, 3) world m of ``track`` on the 30 Hz grid, NaN where absent."""
    k = int(round((frames[-1][0] - T0_NS) / STEP_NS)) + 1
    out = np.full((k, len(NAMES), 3), np.nan)
    for stamp, ids, joints in frames:
        if track in ids:
            out[int(round((stamp - T0_NS) / STEP_NS))] = joints[list(ids).index(track)]
    return out


@pytest.fixture(scope="module")
def known(tmp_path_factory):
    path = tmp_path_factory.mktemp("export") / "game"
    frames = known_frames()
    write_poses_bag(path, frames)
    # the bag holds float32 joints: compare with what a reader decodes
    decoded = [(s, ids, j.astype(np.float32).astype(np.float64)) for s, ids, j in frames]
    return path, decoded


@pytest.mark.slow
def test_trc_per_track_matches_bag(known, tmp_path):
    bag, frames = known
    res = run_export(str(bag), "--format", "trc", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["game_P12.trc", "game_P3.trc", "game_P7.trc"]
    assert "left out 9 untracked person-frame(s)" in res.stdout
    for track in (3, 7, 12):
        trc = parse_trc(tmp_path / f"game_P{track}.trc")
        h = trc["header"]
        assert float(h["DataRate"]) == pytest.approx(FPS, rel=1e-6)
        assert float(h["CameraRate"]) == pytest.approx(FPS, rel=1e-6)
        assert h["Units"] == "mm"
        assert int(h["NumFrames"]) == 10 and int(h["NumMarkers"]) == 13
        assert trc["markers"] == list(NAMES)
        assert list(trc["frames"]) == list(range(1, 11))
        np.testing.assert_allclose(trc["times"], np.arange(10) / FPS, atol=1e-6)
        want = expected_grid(frames, track)[..., [1, 2, 0]] * 1000.0  # Pose2Sim Y-up, mm
        np.testing.assert_array_equal(np.isnan(trc["xyz"]), np.isnan(want))
        np.testing.assert_allclose(trc["xyz"], want, atol=6e-4, equal_nan=True)
    # the dropped grid frame 6 (frame# 7) and track 3's lost elbow in frame 1 are empty
    trc3 = parse_trc(tmp_path / "game_P3.trc")
    assert np.isnan(trc3["xyz"][6]).all()
    assert np.isnan(trc3["xyz"][1, 4]).all() and np.isfinite(trc3["xyz"][1, 3]).all()


#: run in a child: importing opensim overwrites LD_LIBRARY_PATH with PATH (its __init__ does),
#: which would break every later rclpy subprocess of the test session
_OPENSIM_READ = """
import json, math, sys
import opensim
t = opensim.TimeSeriesTableVec3(sys.argv[1])
rows = [[[None if math.isnan(t.getRowAtIndex(k)[j][a]) else t.getRowAtIndex(k)[j][a]
          for a in range(3)] for j in range(t.getNumColumns())] for k in range(t.getNumRows())]
print(json.dumps({"labels": list(t.getColumnLabels()), "units": t.getTableMetaDataAsString("Units"),
                  "rate": t.getTableMetaDataAsString("DataRate"),
                  "times": list(t.getIndependentColumn()), "xyz": rows}))
"""


@pytest.mark.slow
def test_trc_read_by_opensim(known, tmp_path):
    """OpenSim's own TRC reader (TRCFileAdapter) gets the same markers, times and values."""
    if importlib.util.find_spec("opensim") is None:  # find, not import (see _OPENSIM_READ)
        pytest.skip("opensim (test extra) is not installed")
    bag, frames = known
    assert export_main([str(bag), "--format", "trc", "--out", str(tmp_path)]) == 0
    for track in (3, 12):
        res = subprocess.run([sys.executable, "-c", _OPENSIM_READ,
                              str(tmp_path / f"game_P{track}.trc")],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        table = json.loads(res.stdout.strip().splitlines()[-1])
        assert table["labels"] == list(NAMES)
        assert table["units"] == "mm" and float(table["rate"]) == pytest.approx(FPS)
        np.testing.assert_allclose(table["times"], np.arange(10) / FPS, atol=1e-6)
        got = np.array(table["xyz"], dtype=np.float64)  # None -> NaN
        want = expected_grid(frames, track)[..., [1, 2, 0]] * 1000.0
        np.testing.assert_allclose(got, want, atol=6e-4, equal_nan=True)


def test_trc_zup_keeps_world_axes(known, tmp_path):
    bag, frames = known
    assert export_main([str(bag), "--format", "trc", "--out", str(tmp_path), "--trc-axes",
                        "zup"]) == 0
    trc = parse_trc(tmp_path / "game_P7.trc")
    np.testing.assert_allclose(trc["xyz"], expected_grid(frames, 7) * 1000.0, atol=6e-4)


@pytest.mark.slow
def test_c3d_all_tracks_read_back_with_ezc3d(known, tmp_path):
    bag, frames = known
    res = run_export(str(bag), "--format", "c3d", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    c3d = ezc3d.c3d(str(tmp_path / "game.c3d"))
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    assert labels == [f"P{t}_{n}" for t in (3, 7, 12) for n in NAMES]
    assert c3d["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(FPS, rel=1e-6)
    assert c3d["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    pts = c3d["data"]["points"]  # (4, M, K)
    res_ = c3d["data"]["meta_points"]["residuals"][0]  # (M, K)
    assert pts.shape == (4, 39, 10)
    for n, track in enumerate((3, 7, 12)):
        want = expected_grid(frames, track).transpose(2, 1, 0) * 1000.0  # (3, J, K)
        got = pts[:3, n * 13:(n + 1) * 13]
        np.testing.assert_allclose(got, want, atol=6e-4, equal_nan=True)
        missing = np.isnan(want).any(axis=0)
        assert missing.any()
        np.testing.assert_array_equal(res_[n * 13:(n + 1) * 13] == -1, missing)
        assert (res_[n * 13:(n + 1) * 13][~missing] >= 0).all()


@pytest.mark.slow
def test_csv_long_format_matches_bag(known, tmp_path):
    bag, frames = known
    res = run_export(str(bag), "--format", "csv", "--out", str(tmp_path))
    assert res.returncode == 0, res.stderr
    with open(tmp_path / "game.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["stamp_ns", "id", "joint", "x", "y", "z"]
    assert len(rows) == sum(len(ids) for _, ids, _ in frames) * 13
    by_key = {(int(r["stamp_ns"]), int(r["id"]), r["joint"]): r for r in rows}
    for stamp, ids, joints in frames:
        for p, pid in enumerate(ids):
            for j, name in enumerate(NAMES):
                r = by_key[(stamp, int(pid), name)]
                got = [float(r[a]) if r[a] else np.nan for a in "xyz"]
                np.testing.assert_allclose(got, joints[p, j], atol=6e-7, equal_nan=True)
    assert any(int(r["id"]) == wire.UNTRACKED_ID for r in rows)


@pytest.mark.slow
def test_min_frames_drops_short_tracks(known, tmp_path):
    bag, _ = known
    res = run_export(str(bag), "--format", "trc", "--out", str(tmp_path), "--min-frames", "3")
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["game_P3.trc", "game_P7.trc"]
    assert "skipped 1 track(s) seen in fewer than 3 frames: 12" in res.stdout


def test_demo_bag_ground_truth_to_c3d(tmp_path):
    """The shipped demo bag's /maem/gt_poses, exported and read back, equal the bag's."""
    bag = REPO / "bags" / "demo"
    assert export_main([str(bag), "--topic", GT_TOPIC, "--format", "c3d",
                        "--out", str(tmp_path)]) == 0
    c3d = ezc3d.c3d(str(tmp_path / "demo.c3d"))
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    pts = c3d["data"]["points"]
    msgs = read_poses(bag, GT_TOPIC)
    assert pts.shape[2] == len(msgs) == 30
    for k, frame in enumerate(sorted(msgs, key=lambda f: f.stamp_ns)):
        for pid, pj in zip(frame.ids, frame.joints):
            cols = [labels.index(f"P{pid}_{n}") for n in NAMES]
            np.testing.assert_allclose(pts[:3, cols, k].T, pj * 1000.0, atol=6e-4)


@pytest.fixture(scope="module")
def small_image_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("export_bad") / "bag"
    write_poses_bag(bag, known_frames(num_frames=4, dropped=()), images=True)
    return bag


@pytest.mark.parametrize("args, needle", [
    (["--topic", "/nope"], "no topic '/nope'"),
    (["--topic", "/camera_0/camera_info"], "is sensor_msgs/msg/CameraInfo"),
    (["--min-frames", "0"], "--min-frames: 0 must be >= 1"),
    (["--min-frames", "99"], "no tracked person to export"),
    (["--convention", "coco_17"], "13 joints, convention coco_17 has 17"),
])
@pytest.mark.slow
def test_bad_inputs_one_line_exit_2(small_image_bag, tmp_path, args, needle):
    bag = small_image_bag
    res = run_export(str(bag), "--format", "trc", "--out", str(tmp_path / "out"), *args)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr


@pytest.mark.slow
def test_bad_bag_and_out(tmp_path):
    res = run_export(str(tmp_path / "missing"), "--format", "csv", "--out", str(tmp_path))
    assert res.returncode == 2 and "not a rosbag2 folder" in res.stderr
    bag = tmp_path / "bag"
    write_poses_bag(bag, known_frames(num_frames=3, dropped=()))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = run_export(str(bag), "--format", "csv", "--out", str(blocker / "sub"))
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0
    assert "--out" in res.stderr and "cannot create" in res.stderr


@pytest.mark.slow
def test_irregular_and_single_frame_bags(tmp_path):
    frames = known_frames(num_frames=4, dropped=())
    s, ids, j = frames[2]
    frames[2] = (frames[1][0] + STEP_NS // 10, ids, j)  # two stamps on one grid frame
    write_poses_bag(tmp_path / "jitter", frames)
    res = run_export(str(tmp_path / "jitter"), "--format", "c3d", "--out", str(tmp_path))
    assert res.returncode == 2 and "fall on one frame" in res.stderr
    frames = known_frames(num_frames=3, dropped=())
    s, ids, j = frames[1]
    frames[1] = (s, np.where(ids == 7, 3, ids), j)  # two persons with track id 3
    write_poses_bag(tmp_path / "twice", frames)
    res = run_export(str(tmp_path / "twice"), "--format", "c3d", "--out", str(tmp_path))
    assert res.returncode == 2 and f"track id 3 appears twice at stamp {s}" in res.stderr
    write_poses_bag(tmp_path / "one", known_frames(num_frames=1, dropped=()))
    res = run_export(str(tmp_path / "one"), "--format", "trc", "--out", str(tmp_path))
    assert res.returncode == 2 and "a frame rate needs at least 2 stamps" in res.stderr
