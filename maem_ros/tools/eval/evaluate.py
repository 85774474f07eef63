"""maem-eval: run MAEM association + triangulation offline on a scene folder and score it.

maem-eval SCENE_DIR --params config/sportcenter.yaml [--json OUT.json] [--plots DIR]
          [--ablation] [--oracle] [--explain] [--explain-tracks] [--pred OUT.npz]
          [--frames N]
          [--temporal on|off]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from maem_ros.core.association import PAPER_PIPELINE
from maem_ros.core.detections import FrameDetections
from maem_ros.core.interchange import MissingDataError, SceneFolder, det_ids_key
from maem_ros.core.skeleton import SPORTCENTER_13, convert, get_convention
from maem_ros.params import load_node_params
from maem_ros.tools.cli import fail
from maem_ros.tools.eval.options import build_parser
from maem_ros.tools.eval.results import (
    METRIC_KEYS,
    Run,
    format_causes,
    format_id_lines,
    format_table,
    jsonable,
    score_run,
    write_pred,
)

#: the paper's ablation rows (gates, with the configured clustering), the paper's pipeline and
#: its PA-MPJPE matching baseline: association-parameter overrides on top of the params file;
#: the last row is the configuration itself
ABLATION: tuple[tuple[str, dict[str, Any]], ...] = (
    ("PA-MPJPE matching (spectral)", {"clustering": "spectral"}),
    ("paper pipeline (MAEM)", {**PAPER_PIPELINE, "reproj_gate": True, "epipolar_gate": "mesh"}),
    ("reproj only", {"reproj_gate": True, "epipolar_gate": "none"}),
    ("mesh only", {"reproj_gate": False, "epipolar_gate": "mesh"}),
    ("reproj + sparse kpts", {"reproj_gate": True, "epipolar_gate": "sparse"}),
    ("full (reproj + mesh)", {"reproj_gate": True, "epipolar_gate": "mesh"}),
)

# ---- skip accounting --------------------------------------------------------------------------
#: skip kind (key in --json "skips") -> what happened to the input
SKIP_KINDS = {
    "view_without_dets": "camera has no dets/<view>/ npz: left out of every frame",
    "dets_view_without_camera": "dets/<view>/ without cameras/<view>.json: ignored",
    "missing_npz": "no npz for this view and frame: view left out of the frame",
    "corrupt_npz": "unreadable / mis-shaped / NaN npz: view left out of the frame",
    "frame_without_detections": "no readable npz in any view: frame not evaluated",
    "frame_without_gt": "frame beyond the end of gt.npz: not evaluated",
    "pipeline_error": "association/triangulation raised: frame scored with no predictions",
    "gt_masked_joints": "GT joints with mask 0 among present people: excluded from errors",
}


@dataclass
class SkipLog:
    """Counts of skipped inputs, with the first few messages of each kind."""

    counts: Counter = field(default_factory=Counter)
    examples: dict[str, list[str]] = field(default_factory=dict)
    max_examples: int = 3

    def add(self, kind: str, message: str, n: int = 1) -> None:
        self.counts[kind] += n
        ex = self.examples.setdefault(kind, [])
        if len(ex) < self.max_examples:
            ex.append(message)

    def lines(self) -> list[str]:
        out = []
        for kind in sorted(self.counts):
            out.append(f"  {kind}: {self.counts[kind]}  ({SKIP_KINDS.get(kind, '')})")
            out.extend(f"    e.g. {m}" for m in self.examples.get(kind, []))
        return out


# ---- loading and running frames (one configuration's results: tools/eval/results.Run) -------


def to_sportcenter13(joints: np.ndarray, convention: str | None = None) -> np.ndarray:
    """(...,J,3) keypoints in ``convention`` (default: inferred from J: 70 = mhr70) -> (...,13,3)."""
    return convert(joints, SPORTCENTER_13, convention)


def load_gt(folder: SceneFolder) -> tuple[np.ndarray, np.ndarray] | None:
    """(F,P,13,3) world metres (NaN = masked), (F,P,13) mask; None when the folder has no gt.npz."""
    if not folder.has_gt:
        return None
    pose, mask, convention = folder.gt()
    get_convention(convention)  # unknown convention -> ValueError naming it
    xyz = to_sportcenter13(pose[..., :3], convention)
    if convention == "mhr70":
        mask = np.take(mask, SPORTCENTER_13.from_mhr70, axis=-1)  # type: ignore[arg-type]  # defined
    return xyz, mask


def load_frame(
    folder: SceneFolder, views: Sequence[str], frame: int, skips: SkipLog
) -> dict[str, FrameDetections]:
    """Readable detections of one frame by view; missing / corrupt files are logged and left out.

    A frame with no readable view at all is logged once as frame_without_detections (plus any
    corrupt files), not once per missing view.
    """
    out, missing = {}, []
    for view in views:
        try:
            # a camera with a rig time_offset contributes its frame captured nearest this one
            out[view] = folder.detections_at(view, frame)
        except MissingDataError as e:
            missing.append(str(e))
        except ValueError as e:
            skips.add("corrupt_npz", str(e))
    if not out:
        skips.add("frame_without_detections", f"frame {frame}: no readable npz in any view")
    else:
        for message in missing:
            skips.add("missing_npz", message)
    return out


def run_frame(
    run: Run,
    rig,
    frames: Mapping[str, FrameDetections],
    tri_params,
    skips: SkipLog,
    frame: int,
    det_ids: Mapping[str, np.ndarray] | None = None,
):
    """Associate + triangulate one frame for one configuration; append its predictions.

    Returns the AssociationResult (None for the oracle or when the pipeline raised)."""
    from maem_ros.core.association.pipeline import associate
    from maem_ros.core.tracking.temporal import FLAG_TRACKED, TemporalAssociator
    from maem_ros.core.triangulation.ransac import triangulate

    from .explain import oracle_clusters

    result = ids = step = None
    stamp = min(fd.stamp_ns for fd in frames.values())
    try:
        t0 = time.perf_counter()
        if run.oracle:
            clusters = oracle_clusters(rig.names, frames, det_ids or {}, run.assoc.tau_det, run.assoc.k_min)
        elif isinstance(run.tracker, TemporalAssociator):
            step = run.tracker.step(frames, stamp)
            clusters, ids = step.clusters, step.track_ids
        else:
            result = associate(rig, frames, run.assoc)
            clusters = result.clusters
        run.assoc_ms.append(1e3 * (time.perf_counter() - t0))
        poses = triangulate(rig, frames, clusters, tri_params)
        raw = (
            to_sportcenter13(np.asarray(poses.joints, dtype=np.float64))
            if len(poses)
            else np.zeros((0, SPORTCENTER_13.num_joints, 3))
        )
        joints, std, scores, ids = _published(run, poses, stamp, ids, tri_params)
        valid = np.isfinite(joints).all(-1).any(-1)
        tracked = (
            np.asarray(step.flags) & FLAG_TRACKED > 0 if step is not None else np.zeros(len(clusters), bool)
        )
        run.last_clusters = ([c.members for c, v in zip(clusters, valid) if v], tracked[valid], raw[valid])
        run.preds.append(joints[valid])
        run.scores.append(scores[valid])
        run.stds.append(std[valid])
        run.ids.append(np.asarray(ids, np.int64)[valid])
    except ValueError as e:
        skips.add("pipeline_error", f"{run.name}, frame {frame}: {e}")
        run.preds.append(np.zeros((0, SPORTCENTER_13.num_joints, 3)))
        run.scores.append(np.zeros(0))
        run.stds.append(np.zeros((0, SPORTCENTER_13.num_joints)))
        run.ids.append(np.zeros(0, np.int64))
        run.last_clusters = ([], np.zeros(0, bool), run.preds[-1])
    return result


def explain_tracks_run(
    run: Run, rig, det_ids: Mapping[str, np.ndarray], gt: np.ndarray, gt_mask: np.ndarray
) -> None:
    """Add the first causes of this frame's published poses far from their person to
    run.far_causes (--explain-tracks); gt (P,13,3) / gt_mask (P,13): every column of gt.npz."""
    from .explain import explain_poses, member_persons

    members, tracked, raw = run.last_clusters
    persons = [member_persons(m, rig.names, det_ids) for m in members]
    causes = explain_poses(run.preds[-1], raw, persons, tracked, gt, gt_mask)
    run.published += len(causes)
    run.far_causes.update(c for c in causes if c is not None)


def format_far_causes(runs: Sequence[Run]) -> str:
    """Plain-text breakdown of far published poses: one row per configuration."""
    from .explain import TRACK_CAUSES

    head = ["config", "poses", "far"] + list(TRACK_CAUSES)
    body = [
        [r.name, str(r.published), str(sum(r.far_causes.values()))]
        + [str(r.far_causes.get(c, 0)) for c in TRACK_CAUSES]
        for r in runs
    ]
    widths = [max(len(row[i]) for row in [head] + body) for i in range(len(head))]
    return "\n".join(
        "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        for row in [head] + body
    )


def explain_run(
    run: Run,
    result,
    rig,
    det_ids: Mapping[str, np.ndarray],
    gt: np.ndarray,
    gt_mask: np.ndarray,
    gt_index: np.ndarray,
) -> None:
    """Add the causes of this frame's lost GT persons to run.causes (--explain).

    gt / gt_mask: the frame's present GT persons; gt_index: their person index in gt.npz
    (= the ids in det_ids.npz)."""
    from maem_ros.core.metrics.poses import match_frame

    from .explain import explain_frame, row_persons

    _, cols, _ = match_frame(run.preds[-1], gt, gt_mask)
    lost = np.setdiff1d(np.arange(len(gt)), cols)
    if not lost.size:
        return
    if result is None:  # the pipeline raised on this frame
        run.causes["pipeline_error"] += int(lost.size)
        return
    persons = row_persons(result, rig.names, det_ids)
    run.causes.update(explain_frame(result, persons, gt_index[lost], run.assoc.k_min))


# ---- what the triangulation node would publish ---------------------------------------------


def _published(
    run: Run, poses, stamp: int, ids, tri_params
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the triangulation node publishes for one frame's poses: sportcenter_13 joints (P,13,3)
    world m, their std (P,13) m, scores (P,) and track ids (P,) (the post-hoc 3D tracker's when
    ``ids`` is None, as the node does with temporal off), joints filtered over time when the run
    has a joint filter."""
    from maem_ros.core.tracking.joint_filter import filter_and_score

    n = len(poses)
    joints = (
        to_sportcenter13(np.asarray(poses.joints, dtype=np.float64))
        if n
        else np.zeros((0, SPORTCENTER_13.num_joints, 3))
    )
    cov = (
        to_sportcenter13(np.asarray(poses.joint_cov).reshape(n, -1, 9)).reshape(n, -1, 3, 3)
        if n
        else np.zeros((0, SPORTCENTER_13.num_joints, 3, 3))
    )
    if ids is None:
        ids = run.tracker.update(stamp, joints)
    ids = np.asarray(ids, np.int64)
    joints, std, scores = filter_and_score(
        stamp,
        ids,
        joints,
        cov,
        np.asarray(poses.detection_scores),
        run.joint_filter,
        tri_params.pose_score,
        tri_params.score_ref_m,
    )
    return joints, std, scores, ids


# ---- CLI --------------------------------------------------------------------------------------
def load_params(path: str):
    from maem_ros.core.association import AssociationParams
    from maem_ros.core.triangulation.ransac import TriangulationParams

    assoc = AssociationParams.from_mapping(load_node_params(path, "association"))
    tri = TriangulationParams.from_mapping(load_node_params(path, "triangulation"))
    return assoc, tri


def make_tracker(rig, assoc, params_path: str, temporal: str | None):
    """The run's identity source: TemporalAssociator (temporal on) or the post-hoc Tracker with
    the triangulation node's track_* parameters (temporal off)."""
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    from maem_ros.core.tracking.tracks import Tracker

    section = dict(load_node_params(params_path, "association"))
    if temporal is not None:
        section["temporal"] = temporal == "on"
    tp = TemporalParams.from_mapping(section)
    if tp.temporal:
        return TemporalAssociator(rig, assoc, tp)
    tri = load_node_params(params_path, "triangulation")
    return Tracker(
        gate_m=tri.get("track_gate", 0.5),
        min_hits=tri.get("track_min_hits", 3),
        timeout_s=tri.get("track_timeout", 1.0),
    )


def make_joint_filter(params_path: str):
    """The triangulation node's joint filter (its joint_filter* parameters), or None when off."""
    from maem_ros.core.tracking.joint_filter import JointFilterParams

    return JointFilterParams.from_mapping(load_node_params(params_path, "triangulation")).make()


def _rig_option(path):
    """--rig: a rig file in any format the project reads, or None (the scene's cameras/)."""
    if path is None:
        return None
    from maem_ros.core.geometry.camera import Rig

    if not Path(path).exists():
        raise ValueError(f"--rig {str(path)!r}: no such file or folder")
    return Rig.load(path)


def evaluate_scene(args: argparse.Namespace, log=print) -> dict[str, Any]:
    """Run the evaluation described by parsed CLI args; returns the JSON report dict."""
    assoc, tri = load_params(args.params)
    folder = SceneFolder(args.scene, rig=_rig_option(getattr(args, "rig", None)))
    skips = SkipLog()
    gt = load_gt(folder)
    views = _usable_views(folder, skips)
    total = max(folder.num_frames, gt[0].shape[0] if gt is not None else 0)
    n = total if args.frames is None else min(args.frames, total)
    runs, det_ids = _make_runs(args, folder, assoc)
    truth = _run_frames(args, folder, views, runs, tri, gt, det_ids, n, skips)
    report: dict[str, Any] = {
        "scene": str(args.scene),
        "params_file": str(args.params),
        "association_params": assoc.as_mapping(),
        "triangulation_params": dataclasses.asdict(tri),
        "evaluated_frames": truth.frame_ids,
        "frames_considered": n,
    }
    if gt is None:
        log("maem-eval: scene has no gt.npz: predictions only, no metrics")
        report["frames"] = len(truth.frame_ids)
    else:
        log(
            f"scene {str(args.scene)!r}: {len(views)}/{len(folder.views)} views, "
            f"{len(truth.frame_ids)}/{n} frames evaluated, params {args.params}"
        )
        report.update(_score_runs(args, runs, truth, log))
    report["skips"] = dict(skips.counts)
    report["skip_examples"] = skips.examples
    log("skipped / excluded inputs:" if skips.counts else "skipped / excluded inputs: none")
    for line in skips.lines():
        log(line)
    _write_outputs(args, report, runs, truth, folder.rig, n, gt is not None, log)
    return report


@dataclass
class _Truth:
    """The evaluated frames and, per frame, the ground truth of the people present in it."""

    frame_ids: list[int] = field(default_factory=list)
    gts: list[np.ndarray] = field(default_factory=list)  # (P,J,3) world m
    gt_masks: list[np.ndarray] = field(default_factory=list)  # (P,J) bool, joint annotated
    gt_ids: list[np.ndarray] = field(default_factory=list)  # (P,) gt.npz column = identity


def _usable_views(folder: SceneFolder, skips: SkipLog) -> list[str]:
    """The rig's views that have detection files (the others, and detection folders of no
    camera, are counted as skips)."""
    views = []
    for view in folder.views:
        if folder.frame_files(view):
            views.append(view)
        else:
            skips.add("view_without_dets", f"view {view!r}: no npz in dets/{view}/")
    for stray in folder.unknown_det_views():
        skips.add("dets_view_without_camera", f"dets/{stray}/ has no cameras/{stray}.json")
    return views


def _make_runs(
    args: argparse.Namespace, folder: SceneFolder, assoc
) -> tuple[list[Run], dict[str, np.ndarray] | None]:
    """The configurations to run (the full one, the ablation rows, the oracle first) and the
    GT person of every detection when --oracle / --explain need it."""
    rig = folder.rig
    configs = [(name, assoc.replaced(o)) for name, o in ABLATION] if args.ablation else [("full", assoc)]
    if args.explain and args.temporal == "on":
        raise ValueError("--explain breaks down the per-frame association: use --temporal off")
    temporal = "off" if args.explain else args.temporal
    runs = [
        Run(
            name,
            a,
            tracker=make_tracker(rig, a, args.params, temporal),
            joint_filter=make_joint_filter(args.params),
        )
        for name, a in configs
    ]
    det_ids = None
    if args.oracle or args.explain or args.explain_tracks:
        if not folder.has_det_ids:
            raise ValueError(
                f"scene folder {str(args.scene)!r}: --oracle/--explain/--explain-tracks "
                "need det_ids.npz "
                "(the GT person of every detection, as maem-sim writes it)"
            )
        det_ids = folder.det_ids()
    if args.oracle:
        runs.insert(
            0,
            Run(
                "oracle (GT association)",
                assoc,
                oracle=True,
                tracker=make_tracker(rig, assoc, args.params, "off"),
                joint_filter=make_joint_filter(args.params),
            ),
        )
    return runs, det_ids


def _run_frames(
    args: argparse.Namespace,
    folder: SceneFolder,
    views: list[str],
    runs: list[Run],
    tri,
    gt,
    det_ids,
    n: int,
    skips: SkipLog,
) -> _Truth:
    """Every run on the first ``n`` frames (their predictions go into the runs), with --explain
    the cause of each lost person; returns the evaluated frames' ground truth."""
    rig = folder.rig
    truth = _Truth()
    for f in tqdm(range(n), desc="maem-eval", unit="frame", disable=args.quiet, file=sys.stderr):
        if gt is not None and f >= gt[0].shape[0]:
            skips.add("frame_without_gt", f"frame {f} >= {gt[0].shape[0]} GT frames")
            continue
        frames = load_frame(folder, views, f, skips)
        if not frames:
            continue
        ids = (
            {v: det_ids[key] for v in frames if (key := det_ids_key(v, f)) in det_ids}
            if det_ids is not None
            else None
        )
        results = [run_frame(run, rig, frames, tri, skips, f, ids) for run in runs]
        truth.frame_ids.append(f)
        if gt is None:
            continue
        present = gt[1][f].any(-1)
        truth.gts.append(gt[0][f, present])
        truth.gt_masks.append(gt[1][f, present])
        truth.gt_ids.append(np.flatnonzero(present))  # gt.npz column = identity
        masked = int((~gt[1][f, present]).sum())
        if masked:
            skips.add("gt_masked_joints", f"frame {f}: {masked} joints", masked)
        if args.explain:
            assert ids is not None  # --explain loaded det_ids (checked above)
            for run, result in zip(runs, results):
                if not run.oracle:
                    explain_run(
                        run, result, rig, ids, truth.gts[-1], truth.gt_masks[-1], np.flatnonzero(present)
                    )
        if args.explain_tracks:
            assert ids is not None  # --explain-tracks loaded det_ids (checked above)
            for run in runs:
                explain_tracks_run(run, rig, ids, gt[0][f], gt[1][f])
    return truth


def _score_runs(args: argparse.Namespace, runs: list[Run], truth: _Truth, log) -> dict[str, Any]:
    """Metrics of every run against the ground truth, logged as tables; the report's entries."""
    for run in runs:
        run.metrics = score_run(run, truth.gts, truth.gt_masks, truth.gt_ids)
    main_run = runs[-1]
    report: dict[str, Any] = {k: main_run.metrics.get(k) for k in METRIC_KEYS}
    report["per_frame_mpjpe"] = main_run.metrics.get("per_frame_mpjpe", [])
    if args.ablation:
        report["ablation"] = [
            {"name": r.name, **{k: r.metrics.get(k) for k in METRIC_KEYS}} for r in runs if not r.oracle
        ]
    log(format_table([(r.name, r.metrics) for r in runs]))
    log("identities:")
    for line in format_id_lines(runs):
        log(line)
    if args.oracle:
        report["oracle"] = {k: runs[0].metrics.get(k) for k in METRIC_KEYS}
    if args.explain:
        explained = [r for r in runs if not r.oracle]
        report["explain"] = {r.name: dict(r.causes) for r in explained}
        log("lost GT person-frames by first cause:")
        log(format_causes(explained))
    if args.explain_tracks:
        report["explain_tracks"] = {r.name: {"poses": r.published, **r.far_causes} for r in runs}
        log("published poses > 150 mm from their GT person (or matched to none) by first cause:")
        log(format_far_causes(runs))
    return report


def _write_outputs(
    args: argparse.Namespace,
    report: dict[str, Any],
    runs: list[Run],
    truth: _Truth,
    rig,
    n: int,
    has_gt: bool,
    log,
) -> None:
    """--pred, --plots (scenes with ground truth) and --json."""
    if args.pred:
        write_pred(args.pred, runs[-1], truth.frame_ids, n)
        log(f"predictions -> {str(args.pred)!r}")
    if args.plots and has_gt:
        from .plots import write_plots

        written = write_plots(
            args.plots, runs, truth.frame_ids, truth.gts, truth.gt_masks, rig, args.plot_frame
        )
        log(f"plots -> {', '.join(str(p) for p in written)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(jsonable(report), indent=2))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames is not None and args.frames < 1:
        return fail("maem-eval", "--frames must be >= 1")
    try:
        evaluate_scene(args)
    except ValueError as e:  # bad params file, scene folder, rig or GT: nothing to evaluate
        return fail("maem-eval", e)
    return 0


if __name__ == "__main__":
    sys.exit(main())
