"""PNG plots for maem-eval (matplotlib Agg): per-frame MPJPE, AP vs threshold, top-down court view."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from maem_ros.core.geometry.camera import Rig
from maem_ros.core.metrics.poses import average_precision, match_frame, mpjpe
from maem_ros.core.skeleton import SPORTCENTER_13

#: AP curve thresholds, mm
AP_CURVE_MM = np.arange(25, 301, 5)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def ap_curve(
    preds: Sequence[np.ndarray],
    scores: Sequence[np.ndarray],
    gts: Sequence[np.ndarray],
    gt_masks: Sequence[np.ndarray],
    thresholds_mm: np.ndarray = AP_CURVE_MM,
) -> np.ndarray:
    """AP (0..1) at each MPJPE threshold (mm), same definition as evaluate_sequence's AP@d."""
    costs = [
        mpjpe(np.asarray(p)[:, None], np.asarray(g)[None], np.asarray(m)[None]).reshape(len(p), len(g))
        for p, g, m in zip(preds, gts, gt_masks)
    ]
    return np.array([average_precision(costs, scores, t / 1e3) for t in thresholds_mm])


def per_frame_recall(preds, gts, gt_masks) -> np.ndarray:
    """(F,) matched GT people / GT people per frame (NaN for a frame without GT people)."""
    out = []
    for p, g, m in zip(preds, gts, gt_masks):
        out.append(
            len(match_frame(np.asarray(p), np.asarray(g), np.asarray(m))[1]) / len(g) if len(g) else np.nan
        )
    return np.array(out, dtype=float)


def plot_per_frame_mpjpe(path: Path, frame_ids: Sequence[int], runs, gts, gt_masks) -> Path:
    """Per-frame MPJPE of the matched people (top) and per-frame recall (bottom), one line per run."""
    plt = _pyplot()
    fig, (ax, ax_r) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True, height_ratios=[2, 1])
    for run in runs:
        ax.plot(frame_ids, run.metrics.get("per_frame_mpjpe", []), marker=".", lw=1, label=run.name)
        ax_r.plot(frame_ids, 100 * per_frame_recall(run.preds, gts, gt_masks), lw=1, label=run.name)
    ax.set_ylabel("MPJPE, matched (mm)")
    ax.set_title("Per-frame MPJPE (gaps: no person matched) and recall@500mm")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax_r.set_xlabel("frame")
    ax_r.set_ylabel("recall (%)")
    ax_r.set_ylim(0, 105)
    ax_r.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_ap_curve(path: Path, runs, gts, gt_masks) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for run in runs:
        ax.plot(AP_CURVE_MM, 100 * ap_curve(run.preds, run.scores, gts, gt_masks), lw=1.5, label=run.name)
    for d in (75, 100, 125, 150):
        ax.axvline(d, color="grey", lw=0.5, ls=":")
    ax.set_xlabel("MPJPE threshold d (mm)")
    ax.set_ylabel("AP@d (%)")
    ax.set_ylim(0, 101)
    ax.set_title("Average precision against threshold")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _draw_skeletons(ax, people: np.ndarray, color, label: str | None, ls: str = "-", lw: float = 1.2) -> None:
    for i, joints in enumerate(people):
        segs = [joints[[a, b], :2] for a, b in SPORTCENTER_13.bones]
        segs = [seg for seg in segs if np.all(np.isfinite(seg))]
        for k, seg in enumerate(segs):
            ax.plot(
                seg[:, 0], seg[:, 1], color=color, lw=lw, ls=ls, label=label if i == 0 and k == 0 else None
            )
        ok = np.isfinite(joints).all(-1)
        ax.scatter(joints[ok, 0], joints[ok, 1], s=5, color=color, zorder=3)


def _root(people: np.ndarray) -> np.ndarray:
    """(P,2) top-down position: mean of the finite joints."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN person -> NaN position, fine
        return np.nanmean(people[..., :2], axis=-2) if len(people) else np.zeros((0, 2))


def plot_court(
    path: Path, frame: int, gt: np.ndarray, pred: np.ndarray, rig: Rig, max_zoom: int = 12
) -> Path:
    """Top-down (world x-y) view of GT (black) against estimated (red) skeletons, court and cameras.

    Left: the whole court with every person's position (circle = GT, cross = estimate, grey line
    = matched pair). Right: each GT person zoomed to +-1 m with its MPJPE.
    """
    from maem_ros.sim.rigs import court_corners

    plt = _pyplot()
    n_zoom = min(len(gt), max_zoom)
    cols = 3 if n_zoom > 4 else 2
    rows = max(1, int(np.ceil(n_zoom / cols)))
    fig = plt.figure(figsize=(10 + 2.2 * cols, max(6.0, 2.2 * rows)))
    grid = fig.add_gridspec(rows, 1 + cols, width_ratios=[4.5] + [1] * cols)
    ax = fig.add_subplot(grid[:, 0])
    court = court_corners()
    ax.fill(court[:, 0], court[:, 1], color="#e8d7b5", zorder=0)
    ax.plot(*np.vstack([court, court[:1]])[:, :2].T, color="#8a6d3b", lw=1)
    centres = np.array([c.center for c in rig])
    ax.scatter(centres[:, 0], centres[:, 1], marker="^", color="tab:blue", s=40, label="cameras")
    for c, xyz in zip(rig, centres):
        ax.annotate(c.name, xyz[:2], fontsize=7, xytext=(3, 3), textcoords="offset points")
    g_root, p_root = _root(gt), _root(pred)
    cost = (
        mpjpe(pred[:, None], gt[None]).reshape(len(pred), len(gt))
        if len(pred) and len(gt)
        else np.zeros((len(pred), len(gt)))
    )
    best = np.full(len(gt), -1)
    for j in range(len(gt)):
        col = np.where(np.isfinite(cost[:, j]), cost[:, j], np.inf)
        if col.size and col.min() < 0.5:
            best[j] = int(np.argmin(col))
            ax.plot(*np.stack([g_root[j], p_root[best[j]]]).T, color="grey", lw=1)
    ax.scatter(g_root[:, 0], g_root[:, 1], s=60, facecolors="none", edgecolors="black", label="ground truth")
    ax.scatter(p_root[:, 0], p_root[:, 1], s=50, marker="x", color="tab:red", label="estimated")
    _draw_skeletons(ax, gt, "black", None, lw=0.8)
    _draw_skeletons(ax, pred, "tab:red", None, ls="--", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world y (m)")
    ax.set_title(f"Frame {frame}: {len(gt)} GT people, {len(pred)} estimated (top-down)")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3)
    for k in range(n_zoom):
        z = fig.add_subplot(grid[k // cols, 1 + k % cols])
        _draw_skeletons(z, gt[k : k + 1], "black", None)
        err = "missed"
        if best[k] >= 0:
            _draw_skeletons(z, pred[best[k] : best[k] + 1], "tab:red", None, ls="--")
            err = f"{1e3 * cost[best[k], k]:.0f} mm"
        z.set_xlim(g_root[k, 0] - 1, g_root[k, 0] + 1)
        z.set_ylim(g_root[k, 1] - 1, g_root[k, 1] + 1)
        z.set_aspect("equal")
        z.set_title(f"GT {k}: {err}", fontsize=8)
        z.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_plots(
    out_dir: Path, runs, frame_ids: Sequence[int], gts, gt_masks, rig: Rig, plot_frame: int | None = None
) -> list[Path]:
    """All maem-eval PNGs into ``out_dir``; the court view shows the last run (full config)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [
        plot_per_frame_mpjpe(out_dir / "per_frame_mpjpe.png", frame_ids, runs, gts, gt_masks),
        plot_ap_curve(out_dir / "ap_vs_threshold.png", runs, gts, gt_masks),
    ]
    if frame_ids:
        if plot_frame is None or plot_frame not in frame_ids:
            plot_frame = (
                frame_ids[len(frame_ids) // 2]
                if plot_frame is None
                else min(frame_ids, key=lambda f: abs(f - plot_frame))
            )
        i = list(frame_ids).index(plot_frame)
        gt = np.where(gt_masks[i][..., None], gts[i], np.nan)
        written.append(
            plot_court(out_dir / f"court_frame_{plot_frame:06d}.png", plot_frame, gt, runs[-1].preds[i], rig)
        )
    return written
