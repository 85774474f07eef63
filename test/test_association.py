"""MAEM stage 2 on constructed scenes: exact pinhole cameras, exact 3D bodies, known answers."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from maem_ros.core.association import PAPER_PIPELINE, AssociationParams, associate
from maem_ros.core.association.gates import epipolar
from maem_ros.core.association.gates.epipolar_constants import RSQRT_ERR
from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Rig, fundamental_matrix
from maem_ros.core.geometry.multiview import reprojection_errors
from maem_ros.core.geometry.procrustes import pa_mpjpe, pa_mpjpe_finite

from helpers_scene import Person, look_at, pose_frames, ring_rig, two_facing_cameras

V, J = 400, 24
PAPER = PAPER_PIPELINE
BACKENDS = ["numpy"] + (["numba"] if epipolar.have_numba() else [])
#: (backend, precision, rtol and atol (px) of an accepted pair's mean): numba "mixed" sums
#: float32 distances with the hardware 1/sqrt estimate (decisions still exact: its error bound
#: settles them or the pair is redone in float64); its means are within the estimate's
#: relative error bound (on one point up to ~2e-4, averaging down on full meshes)
#: (backend, precision, rtol, atol px) of the full sums against the float64 mean: mixed
#: precision evaluates the line equation in float32, whose terms (coordinates of hundreds to
#: thousands of px) cancel to a small distance: an absolute error of a few 1e-3 px remains
VARIANTS = [("numpy", "float64", 1e-9, 0.0)] + (
    [("numba", "float64", 1e-9, 0.0), ("numba", "mixed", RSQRT_ERR, 5e-3)]
    if epipolar.have_numba() else [])


# ---------------------------------------------------------------------------------------
# scene construction
# ---------------------------------------------------------------------------------------
def as_sets(clusters) -> set:
    return {frozenset(map(tuple, c.members.tolist())) for c in clusters}


def scene(n_people: int = 5, n_cams: int = 4, seed: int = 0):
    rig = ring_rig(n_cams)
    rng = np.random.default_rng(seed)
    pos = []
    while len(pos) < n_people:
        p = rng.uniform(-4, 4, 2)
        if all(np.linalg.norm(p - q) > 1.2 for q in pos):
            pos.append(p)
    bodies = [Person(p, seed * 100 + k, V).at() for k, p in enumerate(pos)]
    per_cam = {c.name: [(b, None, k) for k, b in enumerate(bodies)] for c in rig}
    frames, ids = pose_frames(rig, per_cam, shuffle_seed=seed + 1)
    truth = {frozenset((ci, ids[c.name].index(k)) for ci, c in enumerate(rig))
             for k in range(n_people)}
    return rig, frames, truth


# ---------------------------------------------------------------------------------------
# the noiseless multi-person multi-camera scene
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("options", [
    {}, {"epipolar_gate": "sparse"}, {"epipolar_gate": "none"}, {"reproj_gate": False},
    {"epipolar_distance": "forward"}, {"reproj_reduce": "max"}, {"early_exit": False},
    {"vertex_stride": 3}, {"vertex_count": 50},
] + [{"backend": b} for b in BACKENDS])
def test_noiseless_scene_gives_exactly_the_true_clusters(options):
    rig, frames, truth = scene(5, 4)
    res = associate(rig, frames, AssociationParams.from_mapping({"k_min": 4, **options}))
    assert as_sets(res.clusters) == truth
    for c in res.clusters:
        assert np.all(c.costs < 1e-9)  # exact keypoints: PA-MPJPE 0 between true views
        assert [tuple(m) for m in c.members] == sorted(map(tuple, c.members.tolist()))
    firsts = [tuple(c.members[0]) for c in res.clusters]
    assert firsts == sorted(firsts)
    s = res.stats
    assert s["pairs_considered"] == 6 * 25 and s["matched_pairs"] == 6 * 5
    assert s["rejected_score"] == 0 and s["conflicts_removed"] == 0
    assert s["rejected_reproj"] + s["rejected_epipolar"] <= 150 - 30
    for k in ("t_reproj_ms", "t_epipolar_ms", "t_cost_ms", "t_match_ms", "t_cluster_ms"):
        assert 0 <= s[k] <= s["t_total_ms"]


def test_many_people_many_cameras_with_numpy_and_numba_agree():
    rig, frames, truth = scene(8, 6, seed=3)
    results = [associate(rig, frames, AssociationParams.from_mapping({"k_min": 6, "backend": b})) for b in BACKENDS]
    for res in results:
        assert as_sets(res.clusters) == truth
        assert all(np.isfinite(float(v)) for v in res.stats.values()), res.stats
    assert len({tuple(sorted((k, v) for k, v in r.stats.items() if not k.startswith("t_")))
                for r in results}) == 1


# ---------------------------------------------------------------------------------------
# the gates
# ---------------------------------------------------------------------------------------
def test_same_epipolar_line_is_separated_by_the_reprojection_gate():
    """P2's centre lies exactly on the epipolar line of P1's centre, but the two rays meet
    behind camera b (a low camera looking slightly up): epipolar geometry cannot see this,
    the reprojection gate can (no 3D point reprojects into both views)."""
    rig = Rig([look_at("a", (-10.0, 0.0, 3.0)), look_at("b", (10.0, 0.0, 0.2), (0.0, 0.0, 1.2))])
    A, B = rig["a"].center, rig["b"].center
    c1 = np.array([-1.0, 0.8, 1.3])
    ghost = A + 24.0 / 9.0 * (c1 - A)  # on a's ray through P1, 4 m behind camera b
    assert rig["b"].world_to_camera(ghost)[2] < 0
    c2 = B - 0.5 * (ghost - B)  # 2 m in front of b, same pixel in b as the ghost
    assert rig["b"].world_to_camera(c2)[2] > 0 and rig["a"].world_to_camera(c2)[2] > 0
    p1, p2 = Person(c1[:2], 1, V).at(), Person(c2[:2], 2, V).at()
    for p, c in ((p1, c1), (p2, c2)):
        p.verts += c - p.centre
        p.joints += c - p.centre
        p.centre = c
    F = fundamental_matrix(rig["a"], rig["b"])
    x1a, x2b = rig["a"].project_rectified(c1), rig["b"].project_rectified(c2)
    assert epipolar.point_distances(x1a[None], x2b[None], F, True)[0] < 1e-6  # same line
    Ps = np.stack([rig["a"].P, rig["b"].P])[None]
    assert np.isinf(reprojection_errors(Ps, np.stack([x1a, x2b])[None]))[0]
    true_err = reprojection_errors(Ps, np.stack([x1a, rig["b"].project_rectified(c1)])[None])
    assert true_err[0] < 1e-6

    frames, _ = pose_frames(rig, {"a": [(p1, None), (p2, None)], "b": [(p1, None), (p2, None)]})
    res = associate(rig, frames, AssociationParams(k_min=2, epipolar_gate="none"))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0)}), frozenset({(0, 1), (1, 1)})}
    assert res.stats["rejected_reproj"] == 2  # both cross pairs
    # without the gate (and no epipolar gate) the cross pair is admitted to the matching
    res = associate(rig, frames, AssociationParams(k_min=2, epipolar_gate="none",
                                                   reproj_gate=False))
    assert res.stats["rejected_reproj"] == 0


def test_people_close_in_3d_are_separated_by_the_dense_mesh_gate():
    """P2 stands 0.5 m from P1 inside the epipolar plane of P1's centre: the bbox centres are
    epipolar-consistent and triangulate in front of both cameras (reprojection gate passes),
    but vertex k of P2 is a different body spot than vertex k of P1."""
    rig = two_facing_cameras()
    p1 = Person((0.0, 1.0), 11, V).at()
    plane_n = np.cross(rig["a"].center - p1.centre, rig["b"].center - p1.centre)
    step = np.cross(plane_n, [0.0, 0.0, 1.0])
    p2 = Person((0.0, 0.0), 12, V).at()
    c2 = p1.centre + 0.5 * step / np.linalg.norm(step)
    p2.verts += c2 - p2.centre
    p2.joints += c2 - p2.centre
    p2.centre = c2
    assert np.linalg.norm(p2.centre - p1.centre) == pytest.approx(0.5)
    frames, _ = pose_frames(rig, {"a": [(p1, None), (p2, None)], "b": [(p1, None), (p2, None)]})
    cross = reprojection_errors(np.stack([rig["a"].P, rig["b"].P])[None],
                                np.stack([frames["a"].centers[0], frames["b"].centers[1]])[None])
    assert cross[0] < 1e-6  # the reprojection gate cannot tell them apart
    F = fundamental_matrix(rig["a"], rig["b"])
    d = epipolar.point_distances(frames["a"].verts2d[0], frames["b"].verts2d[1], F, True)
    assert d.mean() > 8.0

    res = associate(rig, frames, AssociationParams(k_min=2))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0)}), frozenset({(0, 1), (1, 1)})}
    assert res.stats["rejected_epipolar"] == 2
    assert res.stats["rejected_reproj"] == 0


# ---------------------------------------------------------------------------------------
# conflicts, K_min, tau_det, empty input
# ---------------------------------------------------------------------------------------
def test_same_camera_conflict_drops_the_member_with_highest_mean_cost():
    """cam0 sees P twice: d0 exact, d1 with a keypoint deformation that cam1's detection
    shares. d1 wins the (0,1) matching, d0 wins (0,2) and (0,3); union-find joins both.
    Mean PA-MPJPE to the rest: d0 -> (delta + delta + 0 + 0)/4, d1 -> (delta + 0 + delta +
    delta)/4, so d1 is dropped."""
    rig = ring_rig(4)
    p = Person((0.5, -0.5), 21, V).at()
    deformed = p.joints + np.random.default_rng(5).normal(0, 0.06, p.joints.shape)
    frames, _ = pose_frames(rig, {"cam0": [(p, None), (p, deformed)], "cam1": [(p, deformed)],
                                 "cam2": [(p, None)], "cam3": [(p, None)]})
    res = associate(rig, frames, AssociationParams.from_mapping({"k_min": 4, **PAPER}))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0), (2, 0), (3, 0)})}
    assert res.stats["conflicts_removed"] == 1
    exact, bent = (rig["cam0"].world_to_camera(x) for x in (p.joints, deformed))
    fwd, back = pa_mpjpe(exact, bent), pa_mpjpe(bent, exact)  # PA-MPJPE is not symmetric
    # remaining costs (member m aligned onto n for m < n): cam0/2/3 exact, cam1 deformed
    np.testing.assert_allclose(res.clusters[0].costs,
                               [fwd / 3, (fwd + 2 * back) / 3, back / 3, back / 3], rtol=1e-6)


def test_clusters_below_k_min_are_dropped():
    rig = ring_rig(4)
    p, q = Person((-2, 0), 31, V).at(), Person((2, 1), 32, V).at()
    per_cam = {"cam0": [(p, None), (q, None)], "cam1": [(p, None), (q, None)],
               "cam2": [(p, None)], "cam3": [(p, None)]}
    frames, _ = pose_frames(rig, per_cam)
    res = associate(rig, frames, AssociationParams(k_min=3))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0), (2, 0), (3, 0)})}
    assert res.stats["clusters_below_k_min"] == 1
    res = associate(rig, frames, AssociationParams(k_min=2))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0), (2, 0), (3, 0)}),
                                     frozenset({(0, 1), (1, 1)})}
    assert res.stats["clusters_below_k_min"] == 0


def test_detections_below_tau_det_are_ignored():
    rig = ring_rig(4)
    p, q = Person((-2, 0), 41, V).at(), Person((2, 1), 42, V).at()
    per_cam = {c.name: [(p, None), (q, None)] for c in rig}
    frames, _ = pose_frames(rig, per_cam, scores={"cam2": [0.5, 0.95]})
    res = associate(rig, frames, AssociationParams(tau_det=0.9, k_min=3))
    assert as_sets(res.clusters) == {frozenset({(0, 0), (1, 0), (3, 0)}),
                                     frozenset({(0, 1), (1, 1), (2, 1), (3, 1)})}
    assert res.stats["rejected_score"] == 3 * 2  # cam2's detection 0 against 3 cameras x 2
    res = associate(rig, frames, AssociationParams(tau_det=0.4, k_min=3))
    assert len(res.clusters) == 2 and all(len(c) == 4 for c in res.clusters)


def test_empty_cameras_and_single_camera_frames():
    rig, frames, truth = scene(3, 4)
    single = associate(rig, {"cam1": frames["cam1"]}, AssociationParams(k_min=2))
    assert single.clusters == [] and single.stats["pairs_considered"] == 0
    none = associate(rig, {}, AssociationParams())
    assert none.clusters == [] and none.stats["t_total_ms"] >= 0
    with_empty = dict(frames, cam2=FrameDetections.empty("cam2", 0, J, 0))
    res = associate(rig, with_empty, AssociationParams(k_min=3))
    assert as_sets(res.clusters) == {frozenset(m for m in t if m[0] != 2) for t in truth}
    all_empty = {c.name: FrameDetections.empty(c.name, 0, J, V) for c in rig}
    assert associate(rig, all_empty, AssociationParams()).clusters == []
    # a missing camera is simply absent
    res = associate(rig, {k: v for k, v in frames.items() if k != "cam0"},
                    AssociationParams(k_min=3))
    assert as_sets(res.clusters) == {frozenset(m for m in t if m[0] != 0) for t in truth}


# ---------------------------------------------------------------------------------------
# params and input validation
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,value", [
    ("tau_det", 1.5), ("tau_det", "0.9"), ("tau_det", float("nan")), ("tau_reproj_bbox", 0.0),
    ("tau_mesh", -1.0), ("tau_mesh", True), ("k_min", 1), ("k_min", 2.5), ("k_min", "4"),
    ("reproj_reduce", "median"), ("epipolar_gate", "dense"), ("epipolar_distance", "both"),
    ("vertex_stride", 0), ("vertex_count", -1), ("early_exit", "yes"), ("reproj_gate", 1),
    ("backend", "gpu"),
])
def test_bad_params_raise_value_error_naming_the_parameter(name, value):
    with pytest.raises(ValueError, match=f"^{name}:"):
        AssociationParams.from_mapping({name: value})


def test_from_mapping_takes_known_keys_of_the_shipped_params():
    from maem_ros.params import load_node_params
    p = AssociationParams.from_mapping(load_node_params("humanm3.yaml", "association"))
    assert (p.tau_det, p.tau_reproj_bbox, p.tau_mesh, p.k_min) == (0.7, 30.0, 8.0, 2)
    p = AssociationParams.from_mapping(load_node_params("sportcenter.yaml", "association"))
    assert (p.tau_det, p.tau_reproj_bbox, p.tau_mesh, p.k_min) == (0.9, 10.0, 8.0, 4)


def test_bad_input_raises_value_error_naming_the_field():
    rig, frames, _ = scene(2, 3)
    params = AssociationParams(k_min=2)
    with pytest.raises(ValueError, match="unknown camera 'nope'"):
        associate(rig, dict(frames, nope=frames["cam0"]), params)
    with pytest.raises(ValueError, match="camera"):
        associate(rig, {"cam0": frames["cam1"]}, params)
    bad = frames["cam0"]
    verts = bad.verts2d.copy()
    verts[1, 7, 0] = np.inf  # NaN is a missing vertex, inf is never valid
    with pytest.raises(ValueError, match="verts2d: inf in detection 1"):
        associate(rig, dict(frames, cam0=FrameDetections("cam0", 0, bad.bboxes, bad.scores,
                                                         bad.kpts2d, bad.kpts3d, verts)), params)
    boxes = bad.bboxes.copy()
    boxes[0, [0, 2]] = boxes[0, [2, 0]]
    with pytest.raises(ValueError, match="bbox: inverted"):
        associate(rig, dict(frames, cam0=FrameDetections("cam0", 0, boxes, bad.scores,
                                                         bad.kpts2d, bad.kpts3d, bad.verts2d)),
                  params)
    with pytest.raises(ValueError, match="kpts2d: cameras disagree"):
        short = FrameDetections("cam0", 0, bad.bboxes, bad.scores, bad.kpts2d[:, :5],
                                bad.kpts3d[:, :5], bad.verts2d)
        associate(rig, dict(frames, cam0=short), params)
    no_mesh = FrameDetections("cam0", 0, bad.bboxes, bad.scores, bad.kpts2d, bad.kpts3d,
                              bad.verts2d[:, :0])
    with pytest.raises(ValueError, match="verts2d: epipolar_gate 'mesh' needs mesh vertices"):
        associate(rig, {"cam0": no_mesh, "cam1": no_mesh.__class__(
            "cam1", 0, bad.bboxes, bad.scores, bad.kpts2d, bad.kpts3d, bad.verts2d[:, :0])},
            params)
    # ... but the sparse gate works without a mesh
    associate(rig, {"cam0": no_mesh}, AssociationParams(k_min=2, epipolar_gate="sparse"))


# ---------------------------------------------------------------------------------------
# the epipolar kernel: exact early exit, backends agree, vertex subsets
# ---------------------------------------------------------------------------------------
def _pairs_near_threshold(seed: int, n: int, tau: float):
    """Random correspondences whose mean distance straddles tau (some just below/above)."""
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (6, n, 3)) + [0, 0, 1]
    xa = rig["a"].project_rectified(X)
    xb = rig["b"].project_rectified(X)
    # move b's points off their epipolar lines by a per-detection amount around tau
    lines = np.einsum("ij,dnj->dni", F, np.concatenate([xa, np.ones((6, n, 1))], -1))
    normal = lines[..., :2] / np.linalg.norm(lines[..., :2], axis=-1, keepdims=True)
    shift = rng.uniform(0.0, 2.0, (6, n, 1)) * rng.uniform(0.5, 1.5, (6, 1, 1)) * tau
    xb = xb + normal * shift * rng.choice([-1, 1], (6, n, 1))
    return F, xa.astype(np.float32), xb.astype(np.float32)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 1500), symmetric=st.booleans(),
       tau=st.floats(0.5, 20.0))
def test_early_exit_decisions_equal_the_full_mean(seed, n, symmetric, tau):
    F, xa, xb = _pairs_near_threshold(seed, n, tau)
    ia, jb = np.repeat(np.arange(6), 6), np.tile(np.arange(6), 6)
    full_mean = epipolar.point_distances(xa[ia], xb[jb], F, symmetric).mean(axis=1)
    reference = full_mean >= tau
    near_tie = np.abs(full_mean - tau) < 1e-9 * tau
    for backend, precision, rtol, atol in VARIANTS:
        for early in (True, False):
            sums, used = epipolar.epipolar_sums(xa, xb, F, ia, jb, tau, symmetric, early, backend,
                                                precision)
            reject = sums >= tau * n
            assert np.array_equal(reject[~near_tie], reference[~near_tie])
            assert np.all(used[~reject] == n)  # accepted pairs are always summed in full
            if not early:
                np.testing.assert_allclose(sums / n, full_mean, rtol=rtol, atol=atol)


def test_early_exit_stops_wrong_pairs_after_few_points():
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    rng = np.random.default_rng(0)
    xa = rng.uniform(0, 1000, (2, 18439, 2)).astype(np.float32)
    xb = rng.uniform(0, 1000, (2, 18439, 2)).astype(np.float32)
    for backend in BACKENDS:
        sums, used = epipolar.epipolar_sums(xa, xb, F, np.array([0, 1]), np.array([1, 0]), 8.0,
                                            backend=backend)
        assert np.all(sums >= 8.0 * 18439) and np.all(used <= 2 * epipolar.BLOCK)


def test_point_at_the_epipole_rejects_the_pair():
    rig = two_facing_cameras()
    F = fundamental_matrix(rig["a"], rig["b"])
    epipole_a = rig["a"].project_rectified(rig["b"].center)
    xa = np.tile(epipole_a, (1, 64, 1)).astype(np.float64)
    xb = np.full((1, 64, 2), 500.0)
    for backend in BACKENDS:
        sums, _ = epipolar.epipolar_sums(xa, xb, F, np.array([0]), np.array([0]), 8.0,
                                         backend=backend)
        assert not sums[0] < 8.0 * 64


def test_vertex_subset_and_block_order():
    assert epipolar.vertex_subset(100) is None
    assert np.array_equal(epipolar.vertex_subset(10, 3), [0, 3, 6, 9])
    sub = epipolar.vertex_subset(18439, 1, 500)
    assert sub.size == 500 and sub[0] == 0 and sub[-1] == 18438 and np.all(np.diff(sub) > 0)
    assert epipolar.vertex_subset(18439, 2, 100000).size == 9220
    blocks = epipolar.block_order(10000)
    covered = np.concatenate([np.arange(s, e) for s, e in blocks])
    assert np.array_equal(np.sort(covered), np.arange(10000))
    assert not np.array_equal(covered, np.arange(10000))  # shuffled
    assert np.array_equal(blocks, epipolar.block_order(10000))  # one fixed order


# ---------------------------------------------------------------------------------------
# the cost
# ---------------------------------------------------------------------------------------
def test_batched_pa_mpjpe_matches_procrustes_and_is_similarity_invariant():
    rng = np.random.default_rng(7)
    X = rng.normal(size=(20, J, 3))
    Y = rng.normal(size=(20, J, 3))
    np.testing.assert_allclose(pa_mpjpe_finite(X, Y), pa_mpjpe(X, Y), rtol=1e-10)
    from scipy.spatial.transform import Rotation
    R = Rotation.random(20, random_state=3).as_matrix()
    Z = 2.5 * np.einsum("sij,skj->ski", R, X) + rng.normal(size=(20, 1, 3))
    np.testing.assert_allclose(pa_mpjpe_finite(Z, X), 0.0, atol=1e-12)
    np.testing.assert_allclose(pa_mpjpe_finite(X, Z), 0.0, atol=1e-11)
    mirrored = X * [1, 1, -1]  # a reflection is not a rotation: non-zero cost
    assert np.all(pa_mpjpe_finite(mirrored, X) > 1e-3)


def test_epipolar_sums_rejects_bad_indices_and_shapes():
    x = np.zeros((2, 64, 2), np.float32)
    with pytest.raises(ValueError, match="out of range"):
        epipolar.epipolar_sums(x, x, np.eye(3), np.array([2]), np.array([0]), 8.0)
    with pytest.raises(ValueError, match="epipolar points"):
        epipolar.epipolar_sums(x, x[:, :10], np.eye(3), np.array([0]), np.array([0]), 8.0)
    with pytest.raises(ValueError, match="^backend:"):
        epipolar.epipolar_sums(x, x, np.eye(3), np.array([0]), np.array([0]), 8.0,
                               backend="cuda")


def test_pa_mpjpe_cost_undefined_below_three_joints():
    """Two joints always align exactly under a similarity: the cost is NaN, i.e. gated."""
    rng = np.random.default_rng(3)
    X, Y = rng.normal(size=(4, 2, 3)), rng.normal(size=(4, 2, 3))
    assert np.all(np.isnan(pa_mpjpe_finite(X, Y)))
    assert np.all(np.isfinite(pa_mpjpe_finite(rng.normal(size=(4, 3, 3)), rng.normal(size=(4, 3, 3)))))


# ---------------------------------------------------------------------------------------
# clustering: consistent vs the paper's transitive union-find
# ---------------------------------------------------------------------------------------
def _chain_case_missing_partner():
    """P seen by cam0..2, Q by cam1..3; Q stands on cam0's ray through P (hidden there) and P
    is hidden in cam3, so P's cam0 detection and Q's cam3 detection pass both gates of pair
    (0, 3) (each with no true partner there; their poses differ): the paper's Hungarian,
    with no bound on the cost, matches them and union-find chains the two people."""
    rig = Rig([look_at("cam0", (-22.0, 0.0, 1.5)), look_at("cam1", (0.0, -22.0, 1.5)),
               look_at("cam2", (0.0, 22.0, 1.5)), look_at("cam3", (16.0, 16.0, 1.5))])
    p = Person((0.0, 0.0), 61, V).at()
    ray = p.centre - rig["cam0"].center
    q = Person(tuple((p.centre + 1.0 * ray / np.linalg.norm(ray))[:2]), 61, V).at()  # same mesh shape
    q.joints = q.centre + (p.joints - p.centre) * [1.0, 1.0, -1.0]  # another pose (upside down)
    frames, _ = pose_frames(rig, {"cam0": [(p, None)], "cam1": [(p, None), (q, None)],
                                 "cam2": [(p, None), (q, None)], "cam3": [(q, None)]})
    truth = {frozenset({(0, 0), (1, 0), (2, 0)}), frozenset({(1, 1), (2, 1), (3, 0)})}
    return rig, frames, truth


def _chain_case_side_by_side():
    """Person-height rig: cam0 and cam1 on one horizontal baseline parallel to the line
    through P and Q (similar poses, side by side), so pair (0, 1) cannot tell P from Q
    geometrically; cam0's monocular 3D poses of the two are swapped, so the (0, 1) Hungarian
    crosses them while every other camera pair matches correctly: union-find chains both."""
    rig = Rig([look_at("cam0", (-15.0, -10.0, 0.9), (0, 0, 0.9)),
               look_at("cam1", (15.0, -10.0, 0.9), (0, 0, 0.9)),
               look_at("cam2", (2.0, 16.0, 1.6), (0, 0, 0.9)),
               look_at("cam3", (-14.0, 9.0, 1.8), (0, 0, 0.9))])
    p, q = Person((-1.5, 0.0), 71, V).at(), Person((1.5, 0.0), 71, V).at()
    q.joints = q.joints + np.random.default_rng(3).normal(0, 0.02, q.joints.shape)
    per_cam = {c.name: [(p, None), (q, None)] for c in rig}
    per_cam["cam0"] = [(p, q.joints - q.centre + p.centre), (q, p.joints - p.centre + q.centre)]
    frames, _ = pose_frames(rig, per_cam)
    truth = {frozenset((c, 0) for c in range(4)), frozenset((c, 1) for c in range(4))}
    return rig, frames, truth


@pytest.mark.parametrize("case", [_chain_case_missing_partner, _chain_case_side_by_side])
def test_consistent_clustering_keeps_apart_what_union_find_chains(case):
    rig, frames, truth = case()
    k_min = 3
    paper = associate(rig, frames, AssociationParams.from_mapping({"k_min": k_min, **PAPER}))
    # the paper's pipeline chains the two people: one cluster, conflicts removed, one lost
    assert paper.stats["conflicts_removed"] >= 1
    assert as_sets(paper.clusters) != truth
    mixed = [g for g in paper.groups if len(g) > 4]
    assert mixed, "union-find should have joined both people into one group"
    consistent = associate(rig, frames, AssociationParams(k_min=k_min))
    assert as_sets(consistent.clusters) == truth
    assert consistent.stats["conflicts_removed"] == 0


def test_cost_cap_and_cost_joints_change_decisions():
    """Two views of P whose 3D poses differ only on joints 0-2 (a bent arm): with the cost on
    every joint the pair costs more than the cap and never matches; on joints 3.. it is
    exact and matches; with the cap off (0, the paper) it matches on any joints."""
    rig = ring_rig(2)
    p = Person((0.3, 0.2), 81, V).at()
    bent = p.joints.copy()
    bent[:3] += [0.6, -0.4, 0.3]
    frames, _ = pose_frames(rig, {"cam0": [(p, None)], "cam1": [(p, bent)]})
    both = {frozenset({(0, 0), (1, 0)})}
    base = dict(k_min=2, tau_cost=0.05)
    res = associate(rig, frames, AssociationParams.from_mapping({"cost_joints": "all", **base}))
    assert res.clusters == [] and res.stats["rejected_cost"] == 1
    rest = ",".join(str(k) for k in range(3, J))
    assert as_sets(associate(rig, frames, AssociationParams.from_mapping({"cost_joints": rest, **base})).clusters) == both
    assert as_sets(associate(rig, frames, AssociationParams.from_mapping({"k_min": 2, **PAPER})).clusters) == both
    # a cap above the pair's cost lets it match with every joint
    full = associate(rig, frames, AssociationParams(k_min=2, cost_joints="all", tau_cost=5.0))
    assert as_sets(full.clusters) == both


def test_body_cost_joints_are_the_sportcenter_joints_of_mhr70():
    from maem_ros.core.skeleton import SPORTCENTER_13_FROM_MHR70
    from maem_ros.core.skeleton import joint_subset as parse_cost_joints
    assert tuple(parse_cost_joints("body", 70)) == SPORTCENTER_13_FROM_MHR70
    assert tuple(parse_cost_joints("all", 5)) == tuple(range(5))
    assert tuple(parse_cost_joints("4,1,2", 5)) == (4, 1, 2)
    for bad in ("1,2", "a,b,c", "1,1,2", 3):
        with pytest.raises(ValueError, match="^cost_joints:"):
            AssociationParams(cost_joints=bad)
    with pytest.raises(ValueError, match="^cost_joints: index 9"):
        parse_cost_joints("0,1,9", 5)


@pytest.mark.parametrize("clustering", ["spectral", "paper", "consistent"])
def test_every_clustering_recovers_a_noiseless_scene(clustering):
    rig, frames, truth = scene(6, 4, seed=3)
    res = associate(rig, frames, AssociationParams(k_min=4, clustering=clustering))
    assert as_sets(res.clusters) == truth


def test_consistent_clustering_never_puts_two_detections_of_one_camera_together():
    rig, frames, _ = scene(6, 5, seed=4)
    rng = np.random.default_rng(0)
    for fd in frames.values():  # heavy 3D pose noise: many close costs, many candidate merges
        fd.kpts3d += rng.normal(0, 0.08, fd.kpts3d.shape)
    res = associate(rig, frames, AssociationParams(k_min=2, tau_cost=0.5, min_support=0.0))
    for g in res.groups:
        cams = res.table.cam[g]
        assert np.unique(cams).size == cams.size
