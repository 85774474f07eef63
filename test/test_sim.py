"""Simulator: rigs, motion, fixed-topology body, exact detections, raw outputs, rendering, config."""
import time

import numpy as np
import pytest

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.skeleton import MHR70_NAMES
from maem_ros.params import resolve_rig_path
from maem_ros.sim import body as body_mod
from maem_ros.sim.noise import PersonState, get_preset, simulate
from maem_ros.sim.rigs import BASKETS, COURT_LENGTH, COURT_WIDTH, RIG_NAMES, build_rig, court_corners
from maem_ros.sim.scene import Scene, SceneConfig
from maem_ros.sim.view import distort_normalised, inside_image, project_raw

N = {n: i for i, n in enumerate(MHR70_NAMES)}


@pytest.fixture(scope="module")
def scene_none():
    return Scene(SceneConfig(rig="sportcenter6", frames=12, difficulty="none", num_vertices=600))


@pytest.fixture(scope="module")
def scene_med():
    return Scene(SceneConfig(rig="sportcenter6", frames=12, difficulty="medium", num_vertices=600, seed=3))


# ---- rigs ------------------------------------------------------------------------------------
def _seen(cam: Camera, X: np.ndarray) -> np.ndarray:
    return inside_image(cam, project_raw(cam, X))


def test_shipped_rig_files_match_the_generator():
    for name in RIG_NAMES:
        shipped, built = Rig.load(resolve_rig_path(name)), build_rig(name)
        assert shipped.names == built.names
        for a, b in zip(shipped, built):
            for attr in ("K", "R", "t", "D"):
                np.testing.assert_allclose(getattr(a, attr), getattr(b, attr), atol=1e-9)
            assert (a.width, a.height) == (b.width, b.height)


def test_sportcenter6_sees_the_court():
    rig = build_rig("sportcenter6")
    assert len(rig) == 6
    for cam in rig:
        assert 1328 <= cam.width <= 1536 and 896 <= cam.height <= 1200
        assert cam.D[0] < -0.3  # strong barrel distortion
        assert 14.0 < np.linalg.norm(cam.center) < 18.5 and cam.center[2] > 5.0
        assert cam.R[2] @ [0, 0, 1] < -0.3  # looking down
        assert _seen(cam, court_corners()).sum() >= 2
    corners_seen = sum(_seen(cam, court_corners()).astype(int) for cam in rig)
    assert np.all(corners_seen >= 4), corners_seen
    # every spot of the court, feet and head height, is seen whole by >= 4 cameras
    gx, gy = np.meshgrid(np.linspace(-COURT_LENGTH / 2, COURT_LENGTH / 2, 15),
                         np.linspace(-COURT_WIDTH / 2, COURT_WIDTH / 2, 8))
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    both = sum((_seen(c, floor) & _seen(c, floor + [0, 0, 2.1])).astype(int) for c in rig)
    assert both.min() >= 4


@pytest.mark.parametrize("name,n", [("humanm3_4", 4), ("humanm3_3", 3)])
def test_humanm3_rigs_see_the_court(name, n):
    rig = build_rig(name)
    assert len(rig) == n
    for cam in rig:
        assert (cam.width, cam.height) == (2048, 1536) and not cam.has_distortion
        assert 1150 < cam.K[0, 0] < 1250
        assert 20.0 < np.linalg.norm(cam.center) < 35.0 and 1.2 < cam.center[2] < 2.2
        assert np.all(_seen(cam, court_corners())) and np.all(_seen(cam, court_corners(z=2.1)))


@pytest.mark.parametrize("model,D", [("plumb_bob", [-0.34, 0.12, -0.004, 0.0008, -0.012]),
                                     ("rational_polynomial", [-0.3, 0.1, 0.001, -0.002, 0.01, 0.05, 0.01, 0.002]),
                                     ("equidistant", [0.05, -0.01, 0.003, -0.001])])
def test_fast_distortion_matches_camera_project(model, D):
    cam = Camera("c", [[700, 0, 640], [0, 705, 480]] + [[0, 0, 1]], np.eye(3), np.zeros(3), 1280, 960, model, D)
    X = np.random.default_rng(0).uniform([-1, -1, 1.5], [1, 1, 3], (500, 3))
    np.testing.assert_allclose(project_raw(cam, X), cam.project(X), atol=1e-6)
    xn = X[:, :2] / X[:, 2:]
    np.testing.assert_allclose(distort_normalised(cam, xn), cam.project(X), atol=1e-6)


# ---- motion and body -------------------------------------------------------------------------
def test_motion_is_plausible():
    sc = Scene(SceneConfig(frames=150, num_vertices=100, seed=1))
    m, dt = sc.motion, 1 / sc.fps
    assert m.pos.shape == (150, 12, 2)
    players = sc.is_player
    assert players.sum() == 10
    assert np.all(m.speed < 8.0)
    acc = np.linalg.norm(np.diff(m.pos, 2, axis=0), axis=-1) / dt ** 2
    assert np.percentile(acc, 99) < 15.0  # smooth: no teleporting
    assert np.all(np.abs(m.pos[:, players, 0]) <= COURT_LENGTH / 2 + 1.0)
    assert np.all(np.abs(m.pos[:, players, 1]) <= COURT_WIDTH / 2 + 1.0)
    assert np.all(np.abs(np.abs(m.pos[:, ~players, 1]) - COURT_WIDTH / 2) < 2.5)  # along the sidelines
    gap = np.linalg.norm(m.pos[:, :, None] - m.pos[:, None], axis=-1) + np.eye(12) * 99
    assert gap.min() > 0.4
    assert (m.speed[:, players] > 4.0).any() and (m.speed[:, players] < 0.5).any()  # running and stopping
    near = np.linalg.norm(m.pos[:, players, None, :] - BASKETS[None, None, :, :2], axis=-1) < 3.0
    assert near.sum(axis=1).max() >= 4  # crowding under a basket
    assert np.ptp(m.height[players]) > 0.1 and np.ptp(m.width) > 0.05


def test_skeleton_is_anatomically_ordered(scene_med):
    for f in (0, 11):
        kp = scene_med.gt_keypoints(f)
        z = kp[..., 2]
        assert np.all(np.isfinite(kp))
        assert np.all(z[:, N["nose"]] > z[:, N["left_shoulder"]])
        assert np.all(z[:, N["left_shoulder"]] > z[:, N["left_hip"]])
        assert np.all(z[:, N["left_hip"]] > z[:, N["left_knee"]])
        assert np.all(z[:, N["right_hip"]] > z[:, N["right_ankle"]] + 0.2)  # (a sprint kicks the heel up)
        assert np.all((z.min(axis=1) > -0.01) & (z.min(axis=1) < 0.05))  # standing on the floor
        for side in ("left", "right"):
            hand = kp[:, [N[n] for n in MHR70_NAMES if n.startswith(side) and ("finger" in n or "thumb" in n
                          or "index" in n or "middle" in n or "ring" in n or "pinky" in n)]]
            assert hand.shape[1] == 20
            assert np.all(np.linalg.norm(hand - kp[:, None, N[f"{side}_wrist"]], axis=-1) < 0.25)
        top = scene_med.vertices(f)[..., 2].max(axis=1)
        assert np.all(np.abs(top - scene_med.motion.height) < 0.25)


def test_fixed_topology_vertex_keeps_its_body_spot(scene_med):
    bm = scene_med.body
    a, b = bm.anchor_a[bm.part_of], bm.anchor_b[bm.part_of]
    dist, axial = [], []
    for f in (0, 5, 11):
        pts, V = scene_med.skeleton(f).points, scene_med.vertices(f)
        A, B = pts[:, a], pts[:, b]
        u = (B - A) / np.linalg.norm(B - A, axis=-1, keepdims=True)
        rel = V - A
        along = np.sum(rel * u, -1)
        dist.append(np.linalg.norm(rel - along[..., None] * u, axis=-1))
        axial.append(along / np.linalg.norm(B - A, axis=-1))
    assert np.ptp(np.stack(dist), axis=0).max() < 1e-9
    assert np.ptp(np.stack(axial), axis=0).max() < 1e-9
    # the poses did change between those frames
    assert np.abs(scene_med.vertices(0) - scene_med.vertices(11)).max() > 0.2


@pytest.mark.parametrize("V", [18439, 600])
def test_vertex_density_follows_a_real_body_mesh(V):
    """Head and hands hold most vertices (SMPL-X: FLAME head 5,023 and MANO hands 778 each of 10,475),
    the torso a minority, unlike an area-proportional surface."""
    bm = body_mod.BodyModel(V)
    share = {n: c / V for n, c in zip(body_mod.PART_NAMES, bm.counts)}
    assert bm.counts.sum() == V and np.all(bm.counts >= 1)
    assert 0.40 <= share["head"] <= 0.45 and 0.46 <= share["head"] + share["neck"] <= 0.50
    for side in "lr":
        assert abs(share[f"hand_{side}"] - 778 / 10475) < 0.003
        assert 0.02 <= share[f"foot_{side}"] <= 0.03
    torso = sum(share[p] for p in ("chest", "abdomen", "pelvis", "shoulders", "hips_band"))
    assert 0.12 <= torso <= 0.2
    # every vertex belongs to one noise group, consistent with its part
    assert bm.group_of.shape == (V,)
    hand = body_mod.NOISE_GROUPS.index("hand")
    assert np.all((bm.group_of == hand) == np.isin(bm.part_of, [body_mod.PART_NAMES.index("hand_l"),
                                                                  body_mod.PART_NAMES.index("hand_r")]))


def test_full_mesh_is_fast():
    sc = Scene(SceneConfig(frames=3))
    assert sc.body.num_vertices == 18439
    sc.vertices(0)
    t = time.perf_counter()
    V = sc.vertices(1)
    assert V.shape == (12, 18439, 3) and np.all(np.isfinite(V))
    assert time.perf_counter() - t < 0.25  # a few ms on a quiet machine; generous for a shared one


# ---- detections --------------------------------------------------------------------------------
def test_difficulty_none_is_exact(scene_none):
    for cam in scene_none.rig.cameras[:3]:
        for f in (0, 7):
            d = scene_none.detections(cam.name, f).validate([c.name for c in scene_none.rig])
            pid = scene_none.detection_persons(cam.name, f)
            assert np.all(pid >= 0) and sorted(pid) == list(range(scene_none.num_persons))  # no miss, no FP
            gt, V = scene_none.gt_keypoints(f)[pid], scene_none.vertices(f)[pid]
            np.testing.assert_allclose(d.kpts2d, cam.project_rectified(gt), atol=1e-6)
            np.testing.assert_allclose(d.kpts3d, cam.world_to_camera(gt), atol=1e-9)
            np.testing.assert_allclose(d.verts2d, cam.project_rectified(V), atol=2e-3)
            assert np.all(d.scores == 0.95)
            assert d.num_joints == 70 and d.num_vertices == 600
            assert d.stamp_ns == scene_none.stamp_ns(f)


def test_raw_outputs_layout_and_raw_vs_rectified(scene_med):
    cam = scene_med.rig["camera_1"]
    outs, d = scene_med.raw_outputs("camera_1", 4), scene_med.detections("camera_1", 4)
    assert len(outs) == d.n > 0
    for i, o in enumerate(outs):
        assert o["bbox"].shape == (4,) and o["pred_keypoints_3d"].shape == (70, 3)
        assert o["pred_keypoints_2d"].shape == (70, 2) and o["pred_keypoints_2d_verts"].shape == (600, 2)
        assert o["pred_vertices"].shape == (600, 3) and o["pred_cam_t"].shape == (3,)
        assert float(o["focal_length"]) == pytest.approx(cam.K[0, 0], rel=1e-6)
        assert float(o["bbox_score"]) == pytest.approx(d.scores[i], abs=1e-6)
        np.testing.assert_allclose(o["pred_keypoints_3d"] + o["pred_cam_t"], d.kpts3d[i], atol=1e-5)
        # raw px undistort back onto the rectified detections
        np.testing.assert_allclose(cam.undistort_points(o["pred_keypoints_2d"].astype(float)), d.kpts2d[i],
                                   atol=0.02)
        np.testing.assert_allclose(cam.undistort_points(o["pred_keypoints_2d_verts"][:50].astype(float)),
                                   d.verts2d[i, :50], atol=0.02)
        box = o["bbox"].astype(float)
        assert 0 <= box[0] <= box[2] <= cam.width - 1 and 0 <= box[1] <= box[3] <= cam.height - 1
        np.testing.assert_allclose(cam.undistort_points(0.5 * (box[:2] + box[2:])), d.centers[i], atol=0.02)
        np.testing.assert_allclose(box[2:] - box[:2], d.bboxes[i, 2:] - d.bboxes[i, :2], atol=1e-3)


@pytest.mark.slow
def test_detections_deterministic_per_seed():
    cfg = dict(rig="humanm3_3", frames=5, num_vertices=200, difficulty="hard")
    a, b = Scene(SceneConfig(**cfg, seed=5)), Scene(SceneConfig(**cfg, seed=5))
    c = Scene(SceneConfig(**cfg, seed=6))
    for cam in ("camera_0", "camera_2"):
        da, db, dc = a.detections(cam, 3), b.detections(cam, 3), c.detections(cam, 3)
        for f in ("bboxes", "scores", "kpts2d", "kpts3d", "verts2d"):
            np.testing.assert_array_equal(getattr(da, f), getattr(db, f))
        assert da.n != dc.n or not np.array_equal(da.kpts2d, dc.kpts2d)
    np.testing.assert_array_equal(a.render("camera_1", 2), b.render("camera_1", 2))
    # different cameras / frames draw different noise
    assert not np.allclose(a.detections("camera_0", 3).scores[:1], a.detections("camera_0", 4).scores[:1])


def _two_people_on_one_ray(cam: Camera, distances=(12.0, 17.0)):
    """PersonState of two people on the optical axis of ``cam`` at these ground distances."""
    c = cam.center
    fwd = cam.R[2].copy()
    fwd[2] = 0
    fwd /= np.linalg.norm(fwd)
    root = np.stack([c[:2] + fwd[:2] * d for d in distances])
    n = len(distances)
    ang = body_mod.gait_angles(np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))
    return PersonState(np.full(n, 1.9), np.ones(n), root, np.zeros(n), ang, np.ones(n, bool))


def test_occluded_person_is_missed_but_found_at_none():
    cam = build_rig("humanm3_4")["camera_0"]
    bm = body_mod.BodyModel(400)
    state = _two_people_on_one_ray(cam)
    skel = body_mod.forward_kinematics(state.height, state.width, state.angles, state.root_xy, state.heading)
    verts = bm.vertices(skel, state.height, state.width)
    for seed in range(5):
        det = simulate(cam, np.random.default_rng(seed), get_preset("medium"), bm, state, skel.points, verts)
        assert 0 in det.person and 1 not in det.person  # the one behind is hidden
    det = simulate(cam, np.random.default_rng(0), get_preset("none"), bm, state, skel.points, verts)
    assert sorted(det.person) == [0, 1]
    # side by side instead: both detected
    state.root_xy[1] = state.root_xy[0] + [1.5 * cam.R[0, 0], 1.5 * cam.R[0, 1]] / np.linalg.norm(cam.R[0, :2])
    skel = body_mod.forward_kinematics(state.height, state.width, state.angles, state.root_xy, state.heading)
    verts = bm.vertices(skel, state.height, state.width)
    det = simulate(cam, np.random.default_rng(1), get_preset("medium"), bm, state, skel.points, verts)
    assert sorted(det.person[det.person >= 0]) == [0, 1]  # (a false positive may come too)


def test_outside_image_is_missed_and_border_boxes_are_truncated():
    cam = build_rig("humanm3_4")["camera_0"]
    bm = body_mod.BodyModel(400)
    state = _two_people_on_one_ray(cam, (14.0, 14.0))
    right = cam.R[0].copy()
    right[2] = 0
    right /= np.linalg.norm(right)
    # person 0 half out of the right border, person 1 far outside the field of view
    half_width = 14.0 * (cam.width - 1 - cam.K[0, 2]) / cam.K[0, 0]
    state.root_xy[0] += right[:2] * (half_width + 0.05)
    state.root_xy[1] += right[:2] * 60.0
    skel = body_mod.forward_kinematics(state.height, state.width, state.angles, state.root_xy, state.heading)
    verts = bm.vertices(skel, state.height, state.width)
    det = simulate(cam, np.random.default_rng(0), get_preset("none"), bm, state, skel.points, verts)
    assert list(det.person) == [0]
    assert det.bbox_raw[0, 2] == pytest.approx(cam.width - 1)  # truncated at the border
    full = cam.project(verts[0])
    assert full[:, 0].max() > cam.width + 5  # the body extends beyond it
    det = simulate(cam, np.random.default_rng(0), get_preset("medium"), bm, state, skel.points, verts)
    assert 1 not in det.person


def test_false_positives_and_bystander_scores():
    sc = Scene(SceneConfig(rig="sportcenter6", frames=30, difficulty="hard", num_vertices=100, seed=2))
    fp, bys, pl = [], [], []
    for f in range(0, 30, 3):
        for cam in sc.rig.names:
            s = sc.simulated(cam, f)
            fp += list(s.scores[s.person < 0])
            known = s.person >= 0
            is_pl = sc.is_player[s.person[known]]
            pl += list(s.scores[known][is_pl])
            bys += list(s.scores[known][~is_pl])
    assert len(fp) > 5 and np.median(fp) < 0.85
    assert np.mean(bys) < np.mean(pl) - 0.05


# ---- rendering ---------------------------------------------------------------------------------
def test_render_draws_people_where_projection_says(scene_none):
    cam = scene_none.rig["camera_3"]
    f = 6
    img = scene_none.render("camera_3", f)
    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
    assert img.std() > 15
    bg = scene_none._renderer.background(cam)
    changed = np.abs(img.astype(int) - bg.astype(int)).sum(axis=2) > 40
    kp = scene_none.gt_keypoints(f)
    chest = 0.5 * (kp[:, N["left_shoulder"]] + kp[:, N["right_hip"]])
    uv = project_raw(cam, chest)
    ok = inside_image(cam, uv, margin=5)
    assert ok.sum() >= 8
    hits = changed[np.round(uv[ok, 1]).astype(int), np.round(uv[ok, 0]).astype(int)]
    assert hits.mean() > 0.9
    # pixels far from every person are untouched background
    far = np.ones(changed.shape, bool)
    allv = project_raw(cam, scene_none.vertices(f).reshape(-1, 3))
    allv = allv[inside_image(cam, allv)]
    cols, rows = np.round(allv[:, 0]).astype(int), np.round(allv[:, 1]).astype(int)
    far[np.clip(rows[:, None] + np.arange(-40, 41), 0, cam.height - 1),
        np.clip(cols[:, None], 0, cam.width - 1)] = False
    assert changed[far].mean() < 0.02
    t = time.perf_counter()
    scene_none.render("camera_3", f + 1)
    assert time.perf_counter() - t < 1.0  # well under 100 ms on a quiet machine


# ---- config and time -----------------------------------------------------------------------------
def test_scene_config_roundtrip_and_validation():
    import json
    cfg = SceneConfig(rig="humanm3_3", frames=7, fps=25.0, seed=4, difficulty="easy", num_vertices=300,
                      players=6, bystanders=1, start_stamp_ns=123)
    back = SceneConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg
    sc = Scene(cfg.to_dict())
    assert sc.gt_keypoints(0).shape == (7, 70, 3) and list(sc.is_player) == [True] * 6 + [False]
    for bad in (dict(frames=0), dict(difficulty="extreme"), dict(fps=-1.0), dict(seed=-2), dict(num_vertices=5)):
        with pytest.raises(ValueError, match=list(bad)[0]):
            SceneConfig(**bad)
    by_path = Scene(SceneConfig(rig=str(resolve_rig_path("humanm3_3")), frames=2, num_vertices=50))
    assert by_path.rig.names == ["camera_0", "camera_1", "camera_2"]
    with pytest.raises(ValueError, match="unknown key"):
        SceneConfig.from_dict({"frame": 3})
    with pytest.raises(ValueError, match="rig"):
        Scene(SceneConfig(rig="no_such_rig", frames=2))


def test_stamps_and_frame_lookup(scene_none):
    s0 = scene_none.stamp_ns(0)
    assert s0 == SceneConfig().start_stamp_ns
    assert scene_none.stamp_ns(3) - s0 == round(3e9 / 30)
    assert scene_none.frame_at(scene_none.stamp_ns(5)) == 5
    assert scene_none.frame_at(scene_none.stamp_ns(5) + 16_000_000) == 5
    assert scene_none.frame_at(scene_none.stamp_ns(5) + 17_000_000) == 6
    assert scene_none.frame_at(s0 - 20_000_000) is None
    assert scene_none.frame_at(scene_none.stamp_ns(11) + 20_000_000) is None
    with pytest.raises(ValueError, match="frame"):
        scene_none.gt_keypoints(12)
    with pytest.raises(ValueError, match="camera"):
        scene_none.detections("camera_9", 0)


def test_tiny_far_away_person_is_missed():
    cam = build_rig("humanm3_4")["camera_0"]
    bm = body_mod.BodyModel(200)
    state = _two_people_on_one_ray(cam, (14.0, 300.0))
    right = cam.R[0, :2] / np.linalg.norm(cam.R[0, :2])
    state.root_xy[1] += right * 60.0  # not hidden behind person 0
    skel = body_mod.forward_kinematics(state.height, state.width, state.angles, state.root_xy, state.heading)
    verts = bm.vertices(skel, state.height, state.width)
    uv = cam.project(verts[1])
    assert np.all(inside_image(cam, uv)) and np.ptp(uv[:, 1]) < 12  # in view, but only a few px tall
    det = simulate(cam, np.random.default_rng(0), get_preset("medium"), bm, state, skel.points, verts)
    assert 0 in det.person and 1 not in det.person
    det = simulate(cam, np.random.default_rng(0), get_preset("none"), bm, state, skel.points, verts)
    assert sorted(det.person) == [0, 1]
