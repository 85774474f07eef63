"""maem-eval --explain-tracks: the first cause of a published pose far from its person, on
constructed frames whose answer is known (tools/explain.explain_poses)."""
from __future__ import annotations

import numpy as np
import pytest

from maem_ros.tools.eval.explain import TRACK_CAUSES, explain_poses, member_persons


def _frame():
    """Two GT people 3 m apart (13 joints each) and a third column absent this frame."""
    rng = np.random.default_rng(0)
    body = rng.uniform(-0.3, 0.3, (13, 3)) + [0, 0, 1.0]
    gt = np.stack([body, body + [3.0, 0, 0], np.full((13, 3), np.nan)])
    mask = np.ones((3, 13), bool)
    mask[2] = False
    return gt, mask


def _one(pub, raw, persons, tracked, gt, mask):
    return explain_poses(np.asarray(pub), np.asarray(raw), persons, np.asarray(tracked), gt,
                         mask)


def test_good_poses_have_no_cause():
    gt, mask = _frame()
    out = _one(gt[:2] + 0.02, gt[:2] + 0.02, [np.array([0, 0, 0]), np.array([1, 1])],
               [True, False], gt, mask)
    assert out == [None, None]


def test_each_cause_on_a_constructed_pose():
    gt, mask = _frame()
    off = np.array([0.0, 0.5, 0.0])  # 500 mm: far (> 150 mm) but still matched (< 500 mm)
    near = gt[0] + 0.01
    cases = {
        # a second pose of person 0, as good as the first: the first holds person 0
        "stale_or_duplicate": ([near, gt[0] + 0.03], [near, gt[0] + 0.03], [[0, 0, 0], [0, 0]],
                               [True, True]),
        # its own triangulation is right, the filter's output is 400 mm off
        "prediction": ([gt[0] + [0, 0.4, 0]], [near], [[0, 0]], [True]),
        # a track took person 1's detection with person 0's
        "wrong_track": ([gt[0] + off * 0.6], [gt[0] + off * 0.6], [[0, 0, 1]], [True]),
        # two views of person 0 only, triangulated 300 mm off
        "weak_two_view": ([gt[0] + off * 0.6], [gt[0] + off * 0.6], [[0, 0]], [True]),
        # the cross-view association mixed a false positive into person 0's cluster
        "wrong_new_cluster": ([gt[0] + off * 0.6], [gt[0] + off * 0.6], [[0, 0, -1]], [False]),
        # three pure views, still far
        "triangulation": ([gt[0] + off * 0.6], [gt[0] + off * 0.6], [[0, 0, 0]], [False]),
        # bystanders (column 3 and beyond are not in gt), 20 m away: matched to none
        "not_in_gt": ([gt[0] + 20.0], [gt[0] + 20.0], [[5, 5, 5]], [False]),
    }
    assert set(cases) == set(TRACK_CAUSES)
    for cause, (pub, raw, persons, tracked) in cases.items():
        out = _one(pub, raw, [np.array(p) for p in persons], tracked, gt, mask)
        assert out[-1] == cause, (cause, out)
        assert all(c is None for c in out[:-1]), (cause, out)


def test_unmatched_pose_of_a_pure_cluster_is_explained():
    """A pose 2 m from everyone (matched to none) of a pure three-view cluster of person 1."""
    gt, mask = _frame()
    pose = gt[1] + [0, 2.0, 0]
    assert _one([pose], [pose], [np.array([1, 1, 1])], [False], gt, mask) == ["triangulation"]


def test_member_persons_reads_det_ids_per_camera():
    det_ids = {"a": np.array([4, -1, 2]), "b": np.array([7])}
    members = np.array([[0, 2], [1, 0], [0, 1], [1, 3]])
    assert member_persons(members, ["a", "b"], det_ids).tolist() == [2, 7, -1, -1]


@pytest.mark.slow
def test_explain_tracks_counts_every_far_pose(tmp_path):
    """On a simulated hard scene, tracks on: the causes sum to the far poses, names are known."""
    import json

    from maem_ros.tools import simulate
    from maem_ros.tools.eval import evaluate
    scene = tmp_path / "scene"
    assert simulate.main([str(scene), "--rig", "humanm3_4", "--frames", "6", "--difficulty",
                          "hard", "--seed", "2", "--quiet"]) == 0
    out = tmp_path / "r.json"
    assert evaluate.main([str(scene), "--params", "humanm3.yaml", "--quiet", "--json", str(out),
                          "--explain-tracks", "--temporal", "on"]) == 0
    rep = json.loads(out.read_text())["explain_tracks"]["full"]
    assert rep["poses"] > 0
    assert set(rep) - {"poses"} <= set(TRACK_CAUSES)
