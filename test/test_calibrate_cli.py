"""maem-calibrate people as users run it: the console script on simulated scene folders."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers_calibrate import aligned_errors
from maem_ros.core.geometry.camera import Rig

BIN = Path(sys.executable).parent


def _run(*args, timeout=600):
    return subprocess.run([str(BIN / "maem-calibrate"), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("calib") / "scene"
    subprocess.run([str(BIN / "maem-sim"), str(out), "--rig", "humanm3_4", "--frames", "12",
                    "--difficulty", "easy", "--vertices", "19", "--intrinsics-only", "--images",
                    "--quiet"], check=True, timeout=600)
    return out


@pytest.mark.slow
def test_people_end_to_end(scene, tmp_path):
    out = tmp_path / "rig.yaml"
    r = _run("people", scene, "--intrinsics", scene / "cameras", "--out", out, "--report",
             tmp_path / "report")
    assert r.returncode == 0, r.stderr
    assert "median px" in r.stdout and "scale from: metric skeletons" in r.stdout
    est, truth = Rig.load(out), Rig.load(scene / "gt_rig.yaml")
    err = aligned_errors(est, truth)
    assert err["rot_median"] < 0.5 and err["rot_max"] < 1.0
    assert err["centre_max"] < 0.02 * err["radius"]
    assert abs(err["scale"] - 1) < 0.1
    assert (tmp_path / "report" / "rig.png").stat().st_size > 10_000
    assert len(list((tmp_path / "report").glob("overlay_*.jpg"))) == 4
    toml = tmp_path / "Calib.toml"  # the Pose2Sim format, read back by the project's reader
    r = _run("people", scene, "--intrinsics", out, "--out", toml, "--no-time")
    assert r.returncode == 0, r.stderr
    back = Rig.load(toml)
    assert aligned_errors(back, truth)["rot_max"] < 1.0


def _one_line_exit_2(r, *words):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    for w in words:
        assert w in lines[0], lines[0]


@pytest.mark.slow
def test_no_intrinsics_for_a_camera(scene, tmp_path):
    intr = tmp_path / "cameras"
    shutil.copytree(scene / "cameras", intr)
    (intr / "camera_2.json").unlink()
    r = _run("people", scene, "--intrinsics", intr, "--out", tmp_path / "rig.yaml")
    _one_line_exit_2(r, "no intrinsics", "camera_2")


@pytest.mark.slow
def test_fewer_than_two_cameras_with_people(scene, tmp_path):
    one = tmp_path / "one"
    shutil.copytree(scene / "cameras", one / "cameras")
    shutil.copytree(scene / "dets" / "camera_0", one / "dets" / "camera_0")
    (one / "scene.json").write_text(json.dumps({"fps": 30.0}))
    r = _run("people", one, "--intrinsics", scene / "cameras", "--out", tmp_path / "rig.yaml")
    _one_line_exit_2(r, "fewer than two cameras")


@pytest.mark.slow
def test_unreadable_court_points(scene, tmp_path):
    bad = tmp_path / "court.yaml"
    bad.write_text("landmarks: [1, 2\n")
    r = _run("people", scene, "--intrinsics", scene / "cameras", "--out", tmp_path / "rig.yaml",
             "--court-points", bad)
    _one_line_exit_2(r, "court points", str(bad))
    r = _run("people", scene, "--intrinsics", scene / "cameras", "--out", tmp_path / "rig.yaml",
             "--court-points", tmp_path / "missing.yaml")
    _one_line_exit_2(r, "court points", "cannot read")
