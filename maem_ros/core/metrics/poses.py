"""Evaluation metrics of the MAEM paper, in the VoxelPose/Panoptic form its tables use.

Inputs are in metres, reported errors in millimetres.

Per-joint rules: a joint counts only where its GT mask is true and both the
prediction and the GT are finite. A predicted NaN joint (not triangulated) is
therefore ignored by MPJPE instead of being penalised; Recall and AP still
penalise poses that are too wrong or missing altogether. A pose pair without any
counted joint has MPJPE NaN and is never matched.

Definitions (per sequence of frames):

- MPJPE(pred, gt) = mean over counted joints of the Euclidean joint distance.
- PA-MPJPE = MPJPE after aligning the prediction to the GT with the least-squares
  similarity (rotation, translation, uniform scale; core/geometry/procrustes.py).
- Matching: per frame, Hungarian assignment (scipy linear_sum_assignment) of
  predictions to GT persons on MPJPE; only pairs with MPJPE < 500 mm are matched
  (pairs at or over 500 mm are priced prohibitively, so the assignment maximises
  the number of such pairs, then minimises their total error).
  mpjpe_* / pa_mpjpe_* are the mean / median over all matched pairs of the sequence;
  per_frame_mpjpe is the mean over the matched pairs of each frame (NaN if none).
- Recall@500 = matched GT persons / all GT persons.
- AP@d, d in {75, 100, 125, 150} mm: all predictions of the sequence are sorted by
  score (descending, stable). Walking that list, a prediction is a true positive if,
  among the GT persons of its frame not yet taken by an earlier prediction at this
  threshold, the closest one (by MPJPE) has MPJPE < d; that GT person is then taken.
  Otherwise it is a false positive. With cumulative TP/FP after each prediction,
  recall_i = TP_i / #GT and precision_i = TP_i / (TP_i + FP_i); precision is replaced
  by its monotone envelope p_i = max_{k >= i} precision_k; with recall padded by 0 in
  front and 1 behind and precision by 0 on both ends, AP = sum over i where recall
  changes of (r_{i+1} - r_i) * p_{i+1}  (the VoxelPose/Panoptic area under the PR curve).
  AP is NaN when the sequence has no GT person.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.geometry.procrustes import pa_mpjpe as _pa_mpjpe

MATCH_THRESHOLD_M = 0.5
AP_THRESHOLDS_MM = (75, 100, 125, 150)
_NO_MATCH = 1e6  # cost standing in for NaN / over-threshold pairs (metres)


def _joint_mask(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    valid = np.isfinite(pred).all(-1) & np.isfinite(gt).all(-1)
    if mask is not None:
        valid = valid & np.asarray(mask, dtype=bool)
    return valid


def mpjpe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(...) mean joint error in metres over joints with GT mask where both are finite.

    pred, gt (...,J,3) metres (broadcast); mask (...,J) bool or None. NaN if no joint counts.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape[-1:] != (3,) or gt.shape[-1:] != (3,):
        raise ValueError(f"mpjpe: pred and gt must be (...,J,3), got {pred.shape} and {gt.shape}")
    valid = _joint_mask(pred, gt, mask)
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(pred - gt, axis=-1)
    n = valid.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(valid, d, 0.0).sum(-1) / n
    return np.where(n > 0, out, np.nan)


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(...) MPJPE in metres after similarity Procrustes of pred onto gt (NaN if < 3 joints)."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    pred, gt = np.broadcast_arrays(pred, gt)
    if mask is not None:
        mask = np.broadcast_to(np.asarray(mask, dtype=bool), pred.shape[:-1])
    return _pa_mpjpe(pred, gt, mask)


def _pairwise_mpjpe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(K,P) MPJPE in metres between every prediction and every GT person."""
    return mpjpe(pred[:, None], gt[None], mask[None])


def match_frame(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, threshold_m: float = MATCH_THRESHOLD_M
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hungarian matching of predictions (K,J,3) to GT (P,J,3) on MPJPE, pairs < threshold only.

    Returns (pred indices, gt indices, MPJPE metres) of the matched pairs.
    """
    cost = _pairwise_mpjpe(pred, gt, mask)
    if cost.size == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    ok = np.isfinite(cost) & (cost < threshold_m)
    rows, cols = linear_sum_assignment(np.where(ok, cost, _NO_MATCH))
    keep = ok[rows, cols]
    return rows[keep], cols[keep], cost[rows[keep], cols[keep]]


def average_precision(
    frame_costs: Sequence[np.ndarray], scores: Sequence[np.ndarray], threshold_m: float
) -> float:
    """AP at one MPJPE threshold (metres) as defined in the module docstring.

    frame_costs[f]: (K_f,P_f) MPJPE metres (NaN = not comparable); scores[f]: (K_f,).
    """
    total_gt = sum(c.shape[1] for c in frame_costs)
    if total_gt == 0:
        return float("nan")
    frame_of = np.concatenate([np.full(len(s), f) for f, s in enumerate(scores)] + [np.zeros(0, int)])
    index_in = np.concatenate([np.arange(len(s)) for s in scores] + [np.zeros(0, int)])
    all_scores = np.concatenate([np.asarray(s, float) for s in scores] + [np.zeros(0)])
    order = np.argsort(-all_scores, kind="stable")
    taken = [np.zeros(c.shape[1], bool) for c in frame_costs]
    tp = np.zeros(len(order))
    for rank, k in enumerate(order):  # greedy in score order: inherently sequential
        f, i = frame_of[k], index_in[k]
        cost = np.where(taken[f] | ~np.isfinite(frame_costs[f][i]), np.inf, frame_costs[f][i])
        if cost.size and cost.min() < threshold_m:
            taken[f][int(np.argmin(cost))] = True
            tp[rank] = 1.0
    ctp = np.cumsum(tp)
    cfp = np.cumsum(1.0 - tp)
    recall = ctp / total_gt
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(ctp + cfp > 0, ctp / (ctp + cfp), 0.0)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # monotone envelope
    precision = np.concatenate([[0.0], precision, [0.0]])
    recall = np.concatenate([[0.0], recall, [1.0]])
    idx = np.nonzero(recall[1:] != recall[:-1])[0]
    return float(np.sum((recall[idx + 1] - recall[idx]) * precision[idx + 1]))


def _check_frame(f: int, pred, score, gt, gmask) -> tuple[np.ndarray, ...]:
    pred = np.asarray(pred, dtype=np.float64)
    score = np.asarray(score, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    gmask = np.asarray(gmask)
    if gt.ndim != 3 or gt.shape[2] != 3:
        raise ValueError(f"gts[{f}]: expected shape (P,J,3), got {gt.shape}")
    J = gt.shape[1]
    if pred.size == 0 and pred.ndim < 3:
        pred = pred.reshape(0, J, 3)
    if pred.ndim != 3 or pred.shape[1:] != (J, 3):
        raise ValueError(f"preds[{f}]: expected shape (K,{J},3), got {pred.shape}")
    if score.shape != (pred.shape[0],):
        raise ValueError(f"scores[{f}]: expected shape ({pred.shape[0]},), got {score.shape}")
    if not np.all(np.isfinite(score)):
        raise ValueError(f"scores[{f}]: contains NaN or inf")
    if gmask.shape != gt.shape[:2]:
        raise ValueError(f"gt_masks[{f}]: expected shape {gt.shape[:2]}, got {gmask.shape}")
    if gmask.dtype != bool and not np.all(np.isin(gmask, (0, 1))):
        raise ValueError(f"gt_masks[{f}]: expected booleans, got values other than 0/1")
    return pred, score, gt, gmask.astype(bool)


def evaluate_sequence(
    preds: Sequence[np.ndarray],
    scores: Sequence[np.ndarray],
    gts: Sequence[np.ndarray],
    gt_masks: Sequence[np.ndarray],
) -> dict:
    """All metrics over a sequence (inputs in metres, errors out in mm; see module docstring).

    preds[f] (K,J,3), scores[f] (K,), gts[f] (P,J,3), gt_masks[f] (P,J) bool.
    Returns frames, recall, mpjpe_mean, mpjpe_median, pa_mpjpe_mean, pa_mpjpe_median (mm),
    ap75, ap100, ap125, ap150 (0..1), per_frame_mpjpe (list, mm, NaN if no match).
    """
    n = len(gts)
    for name, seq in (("preds", preds), ("scores", scores), ("gt_masks", gt_masks)):
        if len(seq) != n:
            raise ValueError(f"{name}: {len(seq)} frames but gts has {n}")
    errs, pa_errs, per_frame, frame_costs, score_list = [], [], [], [], []
    matched_gt = total_gt = 0
    for f in range(n):
        pred, score, gt, gmask = _check_frame(f, preds[f], scores[f], gts[f], gt_masks[f])
        frame_costs.append(_pairwise_mpjpe(pred, gt, gmask))
        score_list.append(score)
        rows, cols, cost = match_frame(pred, gt, gmask)
        total_gt += gt.shape[0]
        matched_gt += len(cols)
        errs.append(cost)
        pa_errs.append(pa_mpjpe(pred[rows], gt[cols], gmask[cols]))
        per_frame.append(float(cost.mean() * 1e3) if len(cost) else float("nan"))
    e = np.concatenate(errs + [np.zeros(0)]) * 1e3
    pa = np.concatenate(pa_errs + [np.zeros(0)]) * 1e3
    pa = pa[np.isfinite(pa)]  # a matched pair with < 3 joints has no Procrustes fit
    out: dict[str, Any] = {
        "frames": n,
        "recall": matched_gt / total_gt if total_gt else float("nan"),
        "mpjpe_mean": float(e.mean()) if e.size else float("nan"),
        "mpjpe_median": float(np.median(e)) if e.size else float("nan"),
        "pa_mpjpe_mean": float(pa.mean()) if pa.size else float("nan"),
        "pa_mpjpe_median": float(np.median(pa)) if pa.size else float("nan"),
    }
    for d in AP_THRESHOLDS_MM:
        out[f"ap{d}"] = average_precision(frame_costs, score_list, d / 1e3)
    out["per_frame_mpjpe"] = per_frame
    return out
