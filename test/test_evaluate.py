"""maem-sim / maem-eval end to end: exact scenes score perfectly, bad inputs are counted skips."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from helpers_scene import exact_scene

from maem_ros.core.interchange import SceneFolder
from maem_ros.tools.eval import evaluate

CONFIG = Path(__file__).resolve().parents[1] / "config"


def run_eval(scene: Path, tmp_path: Path, params: str, *extra: str) -> dict:
    out = tmp_path / "report.json"
    assert evaluate.main([str(scene), "--params", str(CONFIG / params), "--json", str(out), "--quiet",
                          *extra]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_exact_scene_scores_perfectly_with_pred_and_plots(tmp_path):
    folder = exact_scene(tmp_path / "scene")
    pred = tmp_path / "pred.npz"
    rep = run_eval(folder.root, tmp_path, "humanm3.yaml", "--pred", str(pred), "--plots", str(tmp_path / "plots"),
                   "--plot-frame", "2")
    assert set(evaluate.METRIC_KEYS) <= set(rep)
    assert rep["frames"] == 4 and rep["recall"] == 1.0 and rep["ap75"] == 1.0
    # exact views: the per-frame triangulation is exact; the joint filter (on by default) blends
    # in the constant-velocity prediction, weighted by the prior keypoint noise: a few mm
    assert rep["mpjpe_mean"] < 5.0 and rep["pa_mpjpe_mean"] < 5.0
    assert rep["association_ms_median"] > 0
    assert rep["skips"] == {}
    with np.load(pred) as z:
        assert z["pose"].shape == (4, 3, 13, 3) and z["valid"].all() and z["score"].shape == (4, 3)
        gt = SceneFolder(folder.root).gt()[0][..., :3]
        # predictions come in cluster order: match each to its GT person
        for f in range(4):
            d = np.linalg.norm(z["pose"][f][:, None] - gt[f][None], axis=-1).mean(-1)
            assert np.all(d.min(1) < 5e-3)
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert names == ["ap_vs_threshold.png", "court_frame_000002.png", "per_frame_mpjpe.png"]
    assert all((tmp_path / "plots" / n).stat().st_size > 5000 for n in names)


def test_bad_inputs_are_counted_skips_not_crashes(tmp_path, capsys):
    folder = exact_scene(tmp_path / "scene", frames=5)
    root, views = folder.root, folder.views
    (root / "dets" / views[0] / "000001.npz").write_bytes(b"PK\x03\x04 corrupt")           # corrupt npz
    np.savez(root / "dets" / views[1] / "000000.npz", outputs=np.zeros((3, 4)))          # mis-shaped npz
    (root / "dets" / views[1] / "000002.npz").unlink()                                    # missing file
    for v in views[:3]:
        (root / "dets" / v / "000003.npz").unlink()                                       # missing frame 3
    for p in (root / "dets" / views[3]).iterdir():                                        # missing view
        p.unlink()
    pose, mask, conv = SceneFolder(root).gt()
    mask[0, 1, [3, 4]] = False                                                             # masked GT joints
    mask[4] = False                                                                        # nobody in frame 4
    SceneFolder(root).write_gt(pose[:, :, :, :3], mask, conv)
    rep = run_eval(root, tmp_path, "humanm3.yaml", "--frames", "5")
    assert rep["skips"] == {"corrupt_npz": 2, "missing_npz": 1, "view_without_dets": 1,
                            "frame_without_detections": 1, "gt_masked_joints": 2}
    assert rep["evaluated_frames"] == [0, 1, 2, 4] and rep["frames"] == 4
    assert rep["recall"] == 1.0 and rep["mpjpe_mean"] < 1.0
    assert any("000001.npz" in m for m in rep["skip_examples"]["corrupt_npz"])
    err = capsys.readouterr().out
    assert "corrupt_npz: 2" in err and "view_without_dets: 1" in err


def test_frames_beyond_gt_and_bad_files_exit_cleanly(tmp_path, capsys):
    folder = exact_scene(tmp_path / "scene", frames=3, people=2)
    pose, mask, conv = folder.gt()
    folder.write_gt(pose[:2, ..., :3], mask[:2], conv)
    rep = run_eval(folder.root, tmp_path, "humanm3.yaml")
    assert rep["skips"] == {"frame_without_gt": 1} and rep["frames"] == 2
    assert evaluate.main([str(tmp_path / "nowhere"), "--params", str(CONFIG / "humanm3.yaml")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (folder.root / "gt.npz").write_bytes(b"junk")
    assert evaluate.main([str(folder.root), "--params", str(CONFIG / "humanm3.yaml"), "--quiet"]) == 2
    assert "gt.npz" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("association:\n  ros__parameters:\n    tau_det: banana\n")
    assert evaluate.main([str(folder.root), "--params", str(bad)]) == 2
    assert "tau_det" in capsys.readouterr().err


def test_ablation_rows(tmp_path, capsys):
    folder = exact_scene(tmp_path / "scene", frames=2, people=2, vertices=100)
    rep = run_eval(folder.root, tmp_path, "humanm3.yaml", "--ablation")
    assert [r["name"] for r in rep["ablation"]] == [name for name, _ in evaluate.ABLATION]
    assert all(r["recall"] == 1.0 for r in rep["ablation"])
    assert rep["recall"] == rep["ablation"][-1]["recall"]
    out = capsys.readouterr().out
    assert all(name in out for name, _ in evaluate.ABLATION)


@pytest.mark.timeout(120)
def test_zero_noise_sim_scene_through_maem_eval(tmp_path):
    from maem_ros.tools import simulate
    scene = tmp_path / "sim"
    assert simulate.main([str(scene), "--rig", "sportcenter6", "--frames", "3", "--difficulty", "none",
                          "--seed", "0", "--vertices", "2000", "--quiet"]) == 0
    folder = SceneFolder(scene)
    assert folder.num_frames == 3 and len(folder.views) == 6 and folder.info["scene_config"]["seed"] == 0
    pose, mask, conv = folder.gt()
    assert conv == "sportcenter_13" and pose.shape[0] == 3 and mask.all()
    rep = run_eval(scene, tmp_path, "sportcenter.yaml")
    assert rep["frames"] == 3 and rep["skips"] == {}
    assert rep["recall"] == 1.0
    assert rep["mpjpe_mean"] < 1.0 and rep["mpjpe_median"] < 1.0


@pytest.mark.slow
def test_maem_sim_images_and_gt_people(tmp_path, capsys):
    import cv2
    from maem_ros.tools import simulate
    out = tmp_path / "sim"
    assert simulate.main([str(out), "--rig", "humanm3_3", "--frames", "1", "--difficulty", "easy",
                          "--vertices", "100", "--images", "--gt-people", "all", "--quiet"]) == 0
    folder = SceneFolder(out)
    for cam in folder.rig:
        img = cv2.imread(str(folder.image_path(cam.name, 0)))
        assert img is not None and img.shape == (cam.height, cam.width, 3) and img.std() > 5
    pose, mask, _ = folder.gt()
    assert pose.shape[1] == 12 and folder.info["gt_people"] == "all"  # 10 players + 2 bystanders
    assert simulate.main([str(tmp_path / "bad"), "--frames", "0"]) == 2
    assert simulate.main([str(tmp_path / "bad"), "--rig", "no_such_rig", "--frames", "1", "--quiet"]) == 2
    assert "no_such_rig" in capsys.readouterr().err


@pytest.mark.slow
def test_oracle_and_explain_on_simulated_scenes(tmp_path):
    """maem-sim writes det_ids.npz; --oracle scores 100 % on a noiseless scene; on a noisy one
    every lost person-frame gets exactly one cause (the counts add up to the losses)."""
    from maem_ros.tools import simulate
    exact = tmp_path / "exact"
    assert simulate.main([str(exact), "--rig", "humanm3_4", "--frames", "3", "--difficulty", "none",
                          "--vertices", "300", "--quiet"]) == 0
    ids = SceneFolder(exact).det_ids()
    assert set(ids) == {f"{v}/{f:06d}" for v in SceneFolder(exact).views for f in range(3)}
    rep = run_eval(exact, tmp_path, "humanm3.yaml", "--oracle", "--explain")
    assert rep["oracle"]["recall"] == 1.0 and rep["recall"] == 1.0
    assert sum(rep["explain"]["full"].values()) == 0

    noisy = tmp_path / "hard"
    assert simulate.main([str(noisy), "--rig", "humanm3_3", "--frames", "4", "--difficulty", "hard",
                          "--vertices", "300", "--quiet"]) == 0
    rep = run_eval(noisy, tmp_path, "humanm3.yaml", "--oracle", "--explain", "--ablation")
    gt_persons = sum(len(p) for p in [np.load(noisy / "gt.npz")["mask"][f].any(-1).nonzero()[0]
                                      for f in range(4)])
    for row in rep["ablation"]:
        lost = round(gt_persons * (1 - row["recall"]))
        causes = rep["explain"][row["name"]]
        assert sum(causes.values()) == lost, (row["name"], causes)
        assert set(causes) <= set(__import__("maem_ros.tools.eval.explain", fromlist=["CAUSES"]).CAUSES)
    assert rep["oracle"]["recall"] >= max(r["recall"] for r in rep["ablation"]) - 1e-9


def test_explain_and_oracle_need_det_ids(tmp_path, capsys):
    folder = exact_scene(tmp_path / "scene", frames=1)
    assert evaluate.main([str(folder.root), "--oracle", "--quiet"]) == 2
    assert "det_ids.npz" in capsys.readouterr().err
