"""Identity metrics of tracked 3D poses against ground-truth identities: IDF1 and ID switches.

A (GT person, hypothesis) pair *matches* in a frame when both are present and their MPJPE
(core.metrics.poses.mpjpe, GT-masked joints) is below ``threshold_m`` (0.5 m, as Recall@500).

- IDF1 (Ristani et al., ECCV-W 2016, "Performance measures and a data set for multi-target,
  multi-camera tracking"): one global one-to-one assignment of GT trajectories to hypothesis
  trajectories maximising the number of matching frames (IDTP; scipy linear_sum_assignment on
  the (GT, hypothesis) co-occurrence counts). IDFN = GT detections - IDTP, IDFP = hypothesis
  detections - IDTP; IDP = IDTP / (IDTP + IDFP), IDR = IDTP / (IDTP + IDFN),
  IDF1 = 2 IDTP / (2 IDTP + IDFP + IDFN).
- ID switches (CLEAR MOT, Bernardin & Stiefelhagen 2008, as motmetrics counts them): frame by
  frame, a GT person keeps the hypothesis it was matched to in its last matched frame if they
  still match; the others are assigned by Hungarian on MPJPE among matching pairs. A switch is
  counted when a GT person is matched to a hypothesis other than the one it was last matched to.

``players_only``: hypotheses of a frame that match no GT person there (e.g. a tracked referee
when the GT holds the players only) are left out before scoring, so IDF1 is not lowered by
people the GT does not hold; false positives are what AP measures.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.metrics.poses import MATCH_THRESHOLD_M, mpjpe

_NO_MATCH = 1e6


def _frame_distances(gt: np.ndarray, gt_mask: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(P,K) MPJPE (m) between GT persons (P,J,3) and hypotheses (K,J,3); NaN = not comparable."""
    if gt.shape[0] == 0 or pred.shape[0] == 0:
        return np.zeros((gt.shape[0], pred.shape[0]))
    return mpjpe(pred[None], gt[:, None], gt_mask[:, None])


def identity_metrics(
    gt_ids: Sequence[np.ndarray],
    gts: Sequence[np.ndarray],
    gt_masks: Sequence[np.ndarray],
    pred_ids: Sequence[np.ndarray],
    preds: Sequence[np.ndarray],
    threshold_m: float = MATCH_THRESHOLD_M,
    players_only: bool = True,
) -> dict[str, float]:
    """IDF1, IDP, IDR, ID switches over a sequence (see the module docstring).

    Per frame f: gt_ids[f] (P,) int identities, gts[f] (P,J,3) world m, gt_masks[f] (P,J) bool;
    pred_ids[f] (K,) int track ids (< 0 = no id: not a hypothesis), preds[f] (K,J,3) world m.
    Returns idf1, idp, idr (0..1, NaN when undefined), id_switches, idtp, idfp, idfn,
    gt_detections, hyp_detections, hyp_left_out (hypotheses dropped by players_only).
    """
    n = len(gts)
    for name, seq in (("gt_ids", gt_ids), ("gt_masks", gt_masks), ("pred_ids", pred_ids), ("preds", preds)):
        if len(seq) != n:
            raise ValueError(f"{name}: {len(seq)} frames but gts has {n}")
    pairs: dict[tuple[int, int], int] = {}
    gt_count: dict[int, int] = {}
    hyp_count: dict[int, int] = {}
    last: dict[int, int] = {}
    switches = left_out = 0
    for f in range(n):
        g_ids = np.asarray(gt_ids[f], np.int64)
        h_ids = np.asarray(pred_ids[f], np.int64)
        pred = np.asarray(preds[f], np.float64)
        if pred.size == 0:
            pred = np.zeros((0,) + np.shape(gts[f])[1:])
        if len(pred) != len(h_ids):
            raise ValueError(f"preds[{f}]: {len(pred)} poses but pred_ids[{f}] has {len(h_ids)}")
        if len(np.unique(h_ids[h_ids >= 0])) != int((h_ids >= 0).sum()):
            raise ValueError(f"pred_ids[{f}]: a track id appears twice in one frame")
        if len(np.unique(g_ids)) != len(g_ids):
            raise ValueError(f"gt_ids[{f}]: an identity appears twice in one frame")
        hyp = h_ids >= 0
        d = _frame_distances(np.asarray(gts[f], np.float64), np.asarray(gt_masks[f], bool), pred[hyp])
        h_ids = h_ids[hyp]
        ok = np.isfinite(d) & (d < threshold_m)
        if players_only:
            explained = ok.any(0)
            left_out += int((~explained).sum())
            h_ids, d, ok = h_ids[explained], d[:, explained], ok[:, explained]
        for g in g_ids.tolist():
            gt_count[g] = gt_count.get(g, 0) + 1
        for h in h_ids.tolist():
            hyp_count[h] = hyp_count.get(h, 0) + 1
        for r, c in zip(*np.nonzero(ok)):
            key = (int(g_ids[r]), int(h_ids[c]))
            pairs[key] = pairs.get(key, 0) + 1
        switches += _clear_mot_step(g_ids, h_ids, d, ok, last)
    idtp = _global_idtp(pairs)
    n_gt, n_hyp = sum(gt_count.values()), sum(hyp_count.values())
    idfn, idfp = n_gt - idtp, n_hyp - idtp
    div = lambda a, b: a / b if b else float("nan")  # noqa: E731
    return {
        "idf1": div(2 * idtp, 2 * idtp + idfp + idfn),
        "idp": div(idtp, idtp + idfp),
        "idr": div(idtp, idtp + idfn),
        "id_switches": int(switches),
        "idtp": int(idtp),
        "idfp": int(idfp),
        "idfn": int(idfn),
        "gt_detections": int(n_gt),
        "hyp_detections": int(n_hyp),
        "hyp_left_out": int(left_out),
    }


def _clear_mot_step(
    g_ids: np.ndarray, h_ids: np.ndarray, d: np.ndarray, ok: np.ndarray, last: dict[int, int]
) -> int:
    """Match one frame (keep last matches that still hold, Hungarian for the rest); update
    ``last`` (GT id -> hypothesis id of its last match); return the switches of this frame."""
    if d.size == 0:
        return 0
    col_of = {int(h): k for k, h in enumerate(h_ids.tolist())}
    cost = np.where(ok, d, _NO_MATCH)
    kept_rows, kept_cols = [], []
    for r, g in enumerate(g_ids.tolist()):  # one iteration per GT person
        c = col_of.get(last.get(g, -1))
        if c is not None and ok[r, c]:
            kept_rows.append(r)
            kept_cols.append(c)
    free_r = np.setdiff1d(np.arange(len(g_ids)), kept_rows)
    free_c = np.setdiff1d(np.arange(len(h_ids)), kept_cols)
    rows, cols = linear_sum_assignment(cost[np.ix_(free_r, free_c)])
    real = cost[free_r[rows], free_c[cols]] < _NO_MATCH
    switches = 0
    for r, c in zip(free_r[rows[real]].tolist(), free_c[cols[real]].tolist()):
        g, h = int(g_ids[r]), int(h_ids[c])
        if g in last and last[g] != h:
            switches += 1
        last[g] = h
    return switches


def _global_idtp(pairs: dict[tuple[int, int], int]) -> int:
    """Most matching frames any one-to-one GT <-> hypothesis assignment reaches."""
    if not pairs:
        return 0
    gs = sorted({g for g, _ in pairs})
    hs = sorted({h for _, h in pairs})
    gi = {g: i for i, g in enumerate(gs)}
    hi = {h: i for i, h in enumerate(hs)}
    W = np.zeros((len(gs), len(hs)))
    for (g, h), k in pairs.items():
        W[gi[g], hi[h]] = k
    rows, cols = linear_sum_assignment(W, maximize=True)
    return int(W[rows, cols].sum())
