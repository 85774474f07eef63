"""Detection-noise statistics of the simulated SAM 3D Body frontend fall in the documented ranges."""
import numpy as np
import pytest

from maem_ros.core.procrustes import pa_mpjpe
from maem_ros.sim.scene import Scene, SceneConfig


def _stats(rig: str, difficulty: str, frames=range(0, 30, 3)) -> dict[str, np.ndarray]:
    sc = Scene(SceneConfig(rig=rig, difficulty=difficulty, frames=30, num_vertices=800, seed=11))
    out = {k: [] for k in ("pa", "depth", "kp2d", "vert2d", "reproj3d", "player", "bystander", "fp")}
    visible = detected = 0
    for f in frames:
        gt_all, verts_all = sc.gt_keypoints(f), sc.vertices(f)
        for cam in sc.rig:
            s, d = sc.simulated(cam.name, f), sc.detections(cam.name, f)
            real = s.person >= 0
            pid = s.person[real]
            gt = cam.world_to_camera(gt_all[pid])
            out["pa"] += list(pa_mpjpe(d.kpts3d[real], gt))
            r_gt = np.linalg.norm(gt.mean(axis=1), axis=1)
            out["depth"] += list(np.abs(np.linalg.norm(d.kpts3d[real].mean(axis=1), axis=1) - r_gt) / r_gt)
            out["kp2d"] += list(np.median(np.linalg.norm(d.kpts2d[real] - cam.project_rectified(gt_all[pid]),
                                                         axis=-1), axis=1))
            out["vert2d"] += list(np.median(np.linalg.norm(d.verts2d[real] - cam.project_rectified(verts_all[pid]),
                                                           axis=-1), axis=1))
            # 2D is the projection of the 3D estimate (plus small jitter): consistent
            k3 = d.kpts3d[real]
            proj = k3[..., :2] / k3[..., 2:] @ cam.K_rect[:2, :2].T + cam.K_rect[:2, 2]
            out["reproj3d"] += list(np.median(np.linalg.norm(proj - d.kpts2d[real], axis=-1), axis=1))
            pl = sc.is_player[pid]
            out["player"] += list(d.scores[real][pl])
            out["bystander"] += list(d.scores[real][~pl])
            out["fp"] += list(d.scores[~real])
            detected += int(real.sum())
            visible += sc.num_persons
    res = {k: np.asarray(v, dtype=float) for k, v in out.items()}
    res["detected_fraction"] = np.array(detected / visible)
    return res


@pytest.fixture(scope="module")
def medium():
    return _stats("sportcenter6", "medium")


def test_medium_3d_keypoint_error(medium):
    pa_mm = medium["pa"] * 1000
    assert 40.0 <= pa_mm.mean() <= 60.0, pa_mm.mean()


def test_medium_root_depth_error(medium):
    assert 0.05 <= np.median(medium["depth"]) <= 0.15, np.median(medium["depth"])
    assert medium["depth"].max() < 0.45


def test_medium_2d_noise_is_a_few_pixels_and_consistent_with_3d(medium):
    assert 1.0 <= np.median(medium["kp2d"]) <= 6.0, np.median(medium["kp2d"])
    assert 0.5 <= np.median(medium["vert2d"]) <= 6.0, np.median(medium["vert2d"])
    assert np.median(medium["reproj3d"]) < 2.5  # the 2D keypoints are the 3D estimate, projected


def test_medium_scores_and_misses(medium):
    pl, by = medium["player"], medium["bystander"]
    assert np.mean((pl >= 0.85) & (pl <= 0.99)) > 0.8
    assert np.mean(by) < np.mean(pl) and np.any(by > 0.9)
    assert 0.85 < float(medium["detected_fraction"]) < 1.0  # some misses (occlusion), most people found
    assert np.all((medium["fp"] >= 0.25) & (medium["fp"] <= 0.93))


def test_difficulty_orders_the_noise():
    frames = range(0, 30, 10)
    pa = {d: _stats("humanm3_3", d, frames)["pa"].mean() for d in ("none", "easy", "medium", "hard")}
    assert pa["none"] < 1e-9 < pa["easy"] < pa["medium"] < pa["hard"]
    assert 0.02 < pa["easy"] < 0.045 and 0.06 < pa["hard"] < 0.12
