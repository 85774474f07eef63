"""IDF1 and ID switches (core/metrics/identity.py) on hand-made trajectories with hand-computed answers."""
from __future__ import annotations

import numpy as np
import pytest

from maem_ros.core.metrics.identity import identity_metrics

J = 4


def pose(x: float, y: float = 0.0) -> np.ndarray:
    """A (J,3) pose around (x, y)."""
    return np.array([x, y, 1.0]) + np.arange(J)[:, None] * np.array([0.0, 0.0, 0.2])


def sequence(gt_tracks: dict[int, list], hyp_tracks: dict[int, list]):
    """Per frame lists from {id: [position or None per frame]} for GT and hypotheses."""
    n = len(next(iter(gt_tracks.values())))
    out = {k: [] for k in ("gt_ids", "gts", "gt_masks", "pred_ids", "preds")}
    for f in range(n):
        g = [(i, p[f]) for i, p in gt_tracks.items() if p[f] is not None]
        h = [(i, p[f]) for i, p in hyp_tracks.items() if p[f] is not None]
        out["gt_ids"].append(np.array([i for i, _ in g], int))
        out["gts"].append(np.array([pose(*x) for _, x in g]).reshape(-1, J, 3))
        out["gt_masks"].append(np.ones((len(g), J), bool))
        out["pred_ids"].append(np.array([i for i, _ in h], int))
        out["preds"].append(np.array([pose(*x) for _, x in h]).reshape(-1, J, 3))
    return out


def test_perfect_tracking():
    gt = {0: [(0,), (1,), (2,), (3,)], 1: [(5,), (5,), (5,), (5,)]}
    hyp = {7: [(0.05,), (1.05,), (2.05,), (3.05,)], 3: [(5,), (5,), (5,), (5,)]}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["idf1"] == 1.0 and m["id_switches"] == 0 and m["idtp"] == 8


def test_one_switch_halfway():
    """GT 0 is followed by hyp 1 in frames 0-1 and by hyp 2 in frames 2-3; GT 1 by hyp 3.
    Best assignment: 0<->1 (2 frames) or 0<->2 (2), 1<->3 (4): IDTP 6 of 8 + 8 -> IDF1 12/16."""
    gt = {0: [(0,), (1,), (2,), (3,)], 1: [(9,)] * 4}
    hyp = {1: [(0,), (1,), None, None], 2: [None, None, (2,), (3,)], 3: [(9,)] * 4}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["id_switches"] == 1
    assert m["idtp"] == 6 and m["idfp"] == 2 and m["idfn"] == 2
    assert m["idf1"] == pytest.approx(0.75) and m["idp"] == pytest.approx(0.75)


def test_two_ids_exchanged_at_a_crossing_are_two_switches():
    """Two GT people cross at frame 2; the tracker swaps their ids from then on."""
    gt = {0: [(-2,), (-1,), (0, 0.8), (1,), (2,)], 1: [(2,), (1,), (0, -0.8), (-1,), (-2,)]}
    hyp = {10: [(-2,), (-1,), (0, -0.8), (-1,), (-2,)], 11: [(2,), (1,), (0, 0.8), (1,), (2,)]}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["id_switches"] == 2
    # 0<->10 share frames 0,1; 0<->11 share 2,3,4: best IDTP = 3 + 3 = 6 of 10 + 10
    assert m["idtp"] == 6 and m["idf1"] == pytest.approx(12 / 20)


def test_a_switch_back_counts_again_and_a_kept_match_does_not():
    gt = {0: [(0,)] * 5}
    hyp = {1: [(0,), None, (0,), (0,), None], 2: [None, (0,), None, None, (0,)]}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["id_switches"] == 3  # 1 -> 2 -> 1 -> 2
    assert m["idtp"] == 3 and m["idf1"] == pytest.approx(6 / 10)


def test_an_existing_match_is_kept_while_it_holds():
    """hyp 5 follows GT 0; in frame 1 hyp 6 appears closer to GT 0 but 5 still matches: no switch."""
    gt = {0: [(0,), (0,), (0,)]}
    hyp = {5: [(0,), (0.3,), (0,)], 6: [None, (0.01,), None]}
    m = identity_metrics(**sequence(gt, hyp), players_only=False)
    assert m["id_switches"] == 0 and m["idtp"] == 3 and m["idfp"] == 1


def test_missed_frames_lower_idr_not_idp():
    gt = {0: [(0,), (1,), (2,), (3,)]}
    hyp = {4: [(0,), None, None, (3,)]}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["idp"] == 1.0 and m["idr"] == 0.5 and m["idf1"] == pytest.approx(4 / 6)
    assert m["id_switches"] == 0


def test_people_outside_the_gt_are_left_out_players_only():
    """A tracked referee (hyp 9, far from every GT player) does not lower IDF1 players-only."""
    gt = {0: [(0,)] * 4, 1: [(3,)] * 4}
    hyp = {0: [(0,)] * 4, 1: [(3,)] * 4, 9: [(20,)] * 4}
    m = identity_metrics(**sequence(gt, hyp))
    assert m["idf1"] == 1.0 and m["hyp_left_out"] == 4
    m = identity_metrics(**sequence(gt, hyp), players_only=False)
    assert m["idf1"] == pytest.approx(16 / 20) and m["idfp"] == 4


def test_hypotheses_without_id_and_the_threshold():
    gt = {0: [(0,), (0,)]}
    hyp = {-1: [(0,), (0,)]}  # tentative: not a hypothesis
    m = identity_metrics(**sequence(gt, hyp), players_only=False)
    assert m["hyp_detections"] == 0 and m["idf1"] == 0.0
    gt = {0: [(0,), (0,)]}
    hyp = {2: [(0.6,), (0.4,)]}  # 0.6 m is beyond the 0.5 m match threshold
    m = identity_metrics(**sequence(gt, hyp), players_only=False)
    assert m["idtp"] == 1 and m["idfp"] == 1 and m["idfn"] == 1


def test_bad_input_names_the_argument():
    s = sequence({0: [(0,)]}, {1: [(0,)]})
    s["pred_ids"] = []
    with pytest.raises(ValueError, match="pred_ids"):
        identity_metrics(**s)
    s = sequence({0: [(0,)]}, {1: [(0,)], 2: [(1,)]})
    s["pred_ids"][0][:] = 1
    with pytest.raises(ValueError, match="pred_ids\\[0\\]: a track id appears twice"):
        identity_metrics(**s)


def test_agrees_with_motmetrics_when_installed():
    mm = pytest.importorskip("motmetrics")
    rng = np.random.default_rng(0)
    n, people = 30, 4
    gt = {k: [(float(k * 2 + 0.1 * f), float(rng.normal(0, 0.05))) for f in range(n)]
          for k in range(people)}
    hyp = {}
    for k in range(people):  # fragmented, with switches and gaps
        cut = int(rng.integers(5, 25))
        hyp[10 + k] = [gt[k][f] if f < cut and rng.random() > 0.1 else None for f in range(n)]
        hyp[20 + k] = [gt[k][f] if f >= cut and rng.random() > 0.1 else None for f in range(n)]
    s = sequence(gt, hyp)
    ours = identity_metrics(**s, players_only=False)
    acc = mm.MOTAccumulator(auto_id=True)
    for f in range(n):
        d = np.linalg.norm(s["gts"][f][:, None] - s["preds"][f][None], axis=-1).mean(-1)
        acc.update(s["gt_ids"][f].tolist(), s["pred_ids"][f].tolist(), np.where(d < 0.5, d, np.nan))
    summary = mm.metrics.create().compute(acc, metrics=["idf1", "num_switches"])
    assert ours["idf1"] == pytest.approx(float(summary["idf1"].iloc[0]))
    assert ours["id_switches"] == int(summary["num_switches"].iloc[0])
