"""What maem-eval reports of each association configuration (a :class:`Run`): its metrics
(:func:`score_run`: recall, MPJPE, PA-MPJPE, AP, identities; errors in mm), the plain-text tables,
the predictions npz (:func:`write_pred`) and JSON-safe values (:func:`jsonable`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros.core.skeleton import SPORTCENTER_13

METRIC_KEYS = (
    "recall",
    "mpjpe_mean",
    "mpjpe_median",
    "pa_mpjpe_mean",
    "pa_mpjpe_median",
    "ap75",
    "ap100",
    "ap125",
    "ap150",
    "association_ms_median",
    "frames",
    "idf1",
    "idf1_all_hyp",
    "idp",
    "idr",
    "id_switches",
)


@dataclass
class Run:
    """Predictions of one association configuration over the evaluated frames."""

    name: str
    assoc: Any
    oracle: bool = False  # association from det_ids.npz instead of associate()
    preds: list[np.ndarray] = field(default_factory=list)  # per evaluated frame (K,13,3)
    scores: list[np.ndarray] = field(default_factory=list)  # per evaluated frame (K,)
    stds: list[np.ndarray] = field(default_factory=list)  # per evaluated frame (K,13) joint std m
    assoc_ms: list[float] = field(default_factory=list)
    metrics: dict[str, Any] = field(default_factory=dict)
    causes: Counter = field(default_factory=Counter)  # --explain: lost person-frames by cause
    ids: list[np.ndarray] = field(default_factory=list)  # per evaluated frame (K,) track ids
    #: core.tracking.temporal.TemporalAssociator, or core.tracking.tracks.Tracker (post-hoc)
    tracker: Any = None
    joint_filter: Any = None  # core.tracking.joint_filter.JointFilter (None: off)
    #: --explain-tracks: published poses far from their person by first cause, poses published
    far_causes: Counter = field(default_factory=Counter)
    published: int = 0
    #: the last frame's clusters behind its valid poses: members, FLAG_TRACKED, raw joints
    last_clusters: Any = None


def score_run(
    run: Run, gts: list[np.ndarray], gt_masks: list[np.ndarray], gt_ids: list[np.ndarray] | None = None
) -> dict[str, Any]:
    from maem_ros.core.metrics.poses import evaluate_sequence

    m = dict(evaluate_sequence(run.preds, run.scores, gts, gt_masks))
    if gt_ids is not None:
        m.update(score_ids(run, gts, gt_masks, gt_ids))
    m["association_ms_median"] = float(np.median(run.assoc_ms)) if run.assoc_ms else float("nan")
    m["frames"] = len(run.preds)
    return m


def score_ids(
    run: Run, gts: list[np.ndarray], gt_masks: list[np.ndarray], gt_ids: list[np.ndarray]
) -> dict[str, Any]:
    """IDF1 / IDP / IDR / ID switches of the run's track ids (players only, and all hypotheses)."""
    from maem_ros.core.metrics.identity import identity_metrics

    m = identity_metrics(gt_ids, gts, gt_masks, run.ids, run.preds, players_only=True)
    everything = identity_metrics(gt_ids, gts, gt_masks, run.ids, run.preds, players_only=False)
    m["idf1_all_hyp"] = everything["idf1"]
    return m


def _fmt(x: Any, scale: float = 1.0, digits: int = 1) -> str:
    try:
        v = float(x) * scale
    except (TypeError, ValueError):
        return "-"
    return "nan" if not np.isfinite(v) else f"{v:.{digits}f}"


def format_table(rows: Sequence[tuple[str, Mapping[str, Any]]]) -> str:
    """Plain-text table: one row per configuration (Recall / AP in %, errors in mm)."""
    head = [
        "config",
        "frames",
        "Recall%",
        "MPJPE mean",
        "MPJPE med",
        "PA mean",
        "PA med",
        "AP75",
        "AP100",
        "AP125",
        "AP150",
        "assoc ms",
    ]
    body = [
        [
            name,
            str(m.get("frames", "-")),
            _fmt(m.get("recall"), 100),
            _fmt(m.get("mpjpe_mean")),
            _fmt(m.get("mpjpe_median")),
            _fmt(m.get("pa_mpjpe_mean")),
            _fmt(m.get("pa_mpjpe_median")),
            _fmt(m.get("ap75"), 100),
            _fmt(m.get("ap100"), 100),
            _fmt(m.get("ap125"), 100),
            _fmt(m.get("ap150"), 100),
            _fmt(m.get("association_ms_median"), 1, 2),
        ]
        for name, m in rows
    ]
    widths = [max(len(r[i]) for r in [head] + body) for i in range(len(head))]

    def fmt_row(r: tuple[str, ...] | list[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))

    return "\n".join([fmt_row(head), "  ".join("-" * w for w in widths)] + [fmt_row(r) for r in body])


def format_id_lines(runs: Sequence[Run]) -> list[str]:
    """One line per configuration: identity source, IDF1 (players only / all), IDP, IDR, switches."""
    from maem_ros.core.tracking.temporal import TemporalAssociator

    out = []
    for r in runs:
        m = r.metrics
        if "idf1" not in m:
            continue
        source = (
            "track-assisted association"
            if isinstance(r.tracker, TemporalAssociator)
            else "post-hoc 3D tracker"
        )
        out.append(
            f"  {r.name} ({source}): IDF1 {_fmt(m.get('idf1'), 100)}%  "
            f"(all hyp. {_fmt(m.get('idf1_all_hyp'), 100)}%)  IDP {_fmt(m.get('idp'), 100)}%"
            f"  IDR {_fmt(m.get('idr'), 100)}%  ID switches {m.get('id_switches', '-')}"
        )
    return out


def format_causes(runs: Sequence[Run]) -> str:
    """Plain-text loss breakdown: one row per configuration, one column per cause."""
    from .explain import CAUSES

    cols = list(CAUSES) + sorted({c for r in runs for c in r.causes} - set(CAUSES))
    head = ["config", "lost"] + cols
    body = [[r.name, str(sum(r.causes.values()))] + [str(r.causes.get(c, 0)) for c in cols] for r in runs]
    widths = [max(len(row[i]) for row in [head] + body) for i in range(len(head))]

    def fmt_row(row: tuple[str, ...] | list[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))

    return "\n".join([fmt_row(head), "  ".join("-" * w for w in widths)] + [fmt_row(r) for r in body])


def write_pred(path: Path, run: Run, frame_ids: Sequence[int], num_frames: int) -> None:
    """pose (F,K,13,3) world m (NaN = missing), valid (F,K), score (F,K), id (F,K) int64 track id
    (-1 = none), joint_std (F,K,13) m (per-joint standard deviation); F = frames considered."""
    k = max([len(p) for p in run.preds], default=0)
    pose = np.full((num_frames, k, SPORTCENTER_13.num_joints, 3), np.nan)
    valid = np.zeros((num_frames, k), bool)
    score = np.zeros((num_frames, k))
    ids = np.full((num_frames, k), -1, np.int64)
    std = np.full((num_frames, k, SPORTCENTER_13.num_joints), np.nan)
    for f, p, s, i, sd in zip(frame_ids, run.preds, run.scores, run.ids, run.stds):
        pose[f, : len(p)] = p
        valid[f, : len(p)] = True
        score[f, : len(p)] = s
        ids[f, : len(p)] = i
        std[f, : len(p)] = sd
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        np.savez_compressed(
            fh,
            pose=pose,
            valid=valid,
            score=score,
            id=ids,
            joint_std=std,
            convention=np.array(SPORTCENTER_13.name),
        )


def jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    return x
