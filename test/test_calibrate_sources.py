"""maem-calibrate people on the SOURCE kinds besides a scene folder: a bag with
/<cam>/detections, a bag with images and a folder of image folders run through a frontend backend
(synthetic: the simulator's detections regenerated from the recorded scene); each rig is checked
against the scene's true rig. Bad input of those kinds: one line on stderr, exit 2."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers_calibrate import aligned_errors

from maem_ros import bagio
from maem_ros.core.geometry.camera import Rig
from maem_ros.tools.calibrate import calibrate
from maem_ros.tools.bags.make_bag import main as make_bag_main
from maem_ros.tools.simulate import main as sim_main

pytestmark = pytest.mark.slow  # simulated scenes, bags and whole calibrations


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A small rendered scene (4 cameras, 12 frames) and the bag maem-make-bag makes of it
    (images, detections, scene description)."""
    root = tmp_path_factory.mktemp("calib_sources")
    out = root / "scene"
    assert sim_main([str(out), "--rig", "humanm3_4", "--frames", "12", "--difficulty", "easy",
                     "--vertices", "19", "--images", "--quiet"]) == 0
    assert make_bag_main([str(root / "bag"), "--scene", str(out), "--quiet"]) == 0
    return out


def _calibrate(capsys, *args) -> tuple[int, str, str]:
    code = calibrate.main(["people", *map(str, args)])
    got = capsys.readouterr()
    return code, got.out, got.err


def _within_targets(rig_path: Path, scene: Path) -> None:
    err = aligned_errors(Rig.load(rig_path), Rig.load(scene / "gt_rig.yaml"))
    assert err["rot_median"] < 0.5 and err["rot_max"] < 1.0, err
    assert err["centre_max"] < 0.02 * err["radius"], err
    assert abs(err["scale"] - 1) < 0.1, err


def test_bag_with_detections(scene, tmp_path, capsys):
    bag = scene.parent / "bag"
    assert {f"/camera_{k}/detections" for k in range(4)} <= set(bagio.bag_info(bag).topics)
    code, out, err = _calibrate(capsys, bag, "--intrinsics", scene / "cameras", "--out",
                                tmp_path / "rig.yaml", "--reference", scene / "gt_rig.yaml")
    assert code == 0, err
    assert "against reference" in out and "relative rotation deg" in out
    _within_targets(tmp_path / "rig.yaml", scene)


def test_bag_images_through_synthetic_backend(scene, tmp_path, capsys):
    """--backend with a bag: its images go through the backend (scene from the bag), and
    --save-detections writes a detections bag that calibrates to the same rig."""
    saved = tmp_path / "dets_bag"
    code, _, err = _calibrate(capsys, scene.parent / "bag", "--intrinsics", scene / "cameras",
                              "--backend", "synthetic", "--out", tmp_path / "rig.yaml",
                              "--save-detections", saved, "--no-time")
    assert code == 0, err
    _within_targets(tmp_path / "rig.yaml", scene)
    assert {f"/camera_{k}/detections" for k in range(4)} <= set(bagio.bag_info(saved).topics)
    code, _, err = _calibrate(capsys, saved, "--intrinsics", scene / "cameras", "--out",
                              tmp_path / "again.yaml", "--no-time")
    assert code == 0, err
    a, b = Rig.load(tmp_path / "rig.yaml"), Rig.load(tmp_path / "again.yaml")
    assert max(np.abs(a[n].R - b[n].R).max() for n in a.names) < 1e-6


def test_image_folders_through_synthetic_backend(scene, tmp_path, capsys):
    """A folder of <camera>/*.jpg through --backend synthetic; the backend's scene comes from
    --frontend-params (frame k is stamped k / fps from 0)."""
    info = json.loads((scene / "scene.json").read_text())
    params = tmp_path / "synthetic.yaml"
    params.write_text(yaml.safe_dump({"/**/frontend": {"ros__parameters": {
        "backend": "synthetic", "scene_dict": json.dumps(info["scene_config"]),
        "start_stamp_ns": 0}}}))
    code, out, err = _calibrate(capsys, scene / "images", "--intrinsics", scene / "cameras",
                                "--backend", "synthetic", "--frontend-params", params,
                                "--fps", info["fps"], "--out", tmp_path / "rig.yaml",
                                "--report", tmp_path / "report")
    assert code == 0, err
    _within_targets(tmp_path / "rig.yaml", scene)
    assert len(list((tmp_path / "report").glob("overlay_*.jpg"))) == 4  # images to overlay


def _one_line_exit_2(code: int, err: str, *words: str) -> None:
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], lines[0]


def test_bad_inputs_of_bags_and_folders(scene, tmp_path, capsys):
    intr = scene / "cameras"
    out = tmp_path / "rig.yaml"
    empty = tmp_path / "empty_bag"  # a bag with neither detections nor images
    w = bagio.BagWriter(empty)
    w.write(bagio.SCENE_TOPIC, bagio.string_msg("{}"), 1)
    w.close()
    _one_line_exit_2(*_calibrate(capsys, empty, "--intrinsics", intr, "--out", out)[::2],
                     "no /<camera>/detections", str(empty))
    images_only = tmp_path / "images_bag"  # images, but no scene for the synthetic backend
    assert make_bag_main([str(images_only), "--frames-dir", str(scene / "images"), "--rig",
                          str(intr), "--fps", "30", "--quiet"]) == 0
    _one_line_exit_2(*_calibrate(capsys, images_only, "--intrinsics", intr, "--backend",
                                 "synthetic", "--out", out)[::2], "no scene description")
    _one_line_exit_2(*_calibrate(capsys, scene.parent / "bag", "--intrinsics", intr,
                                 "--backend", "no_such_backend", "--out", out)[::2],
                     "--backend no_such_backend", "unknown")
    _one_line_exit_2(*_calibrate(capsys, scene.parent / "bag", "--intrinsics", intr, "--out",
                                 out, "--save-detections", scene)[::2], "already exists")
    broken = tmp_path / "folders"  # an image folder with a file that is no image
    (broken / "camera_0").mkdir(parents=True)
    (broken / "camera_0" / "000000.jpg").write_bytes(b"not a jpeg")
    _one_line_exit_2(*_calibrate(capsys, broken, "--intrinsics", intr, "--backend", "synthetic",
                                 "--out", out)[::2], "unreadable", "000000.jpg")
    _one_line_exit_2(*_calibrate(capsys, scene.parent / "bag", "--intrinsics", intr, "--out",
                                 out, "--reference", tmp_path / "missing.yaml")[::2],
                     "--reference", "no such file")
