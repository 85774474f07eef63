"""Pose2Sim Demo_MultiPerson: the graph's association (track-assisted, core.tracking.temporal)
against the offline per-frame one (core.association.associate) on the same frontend outputs.

    python scripts/pose2sim_association_compare.py OUT [--frames N] [--verify MODE ...]

Runs the mediapipe frontend (config/mediapipe.yaml) once over the four videos and keeps its
detections in OUT/detections.pkl (reused on later runs), then associates every frame set in
stamp order both ways and measures as maem-pose2sim-demo does (tools/demo/demo_metrics: the
clusters triangulated with the triangulation node's parameters, reprojection px over every
finite (joint, kept member view)). Prints one row per association and the frames where the two
differ (members per cluster, per-frame mean reprojection). ``--verify``: the track stage's
verify_epipolar values to run (default association and mesh).
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

from maem_ros.core.association import AssociationParams, associate
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
from maem_ros.core.triangulation.ransac import TriangulationParams, pad_members
from maem_ros.params import load_node_params
from maem_ros.tools.demo import demo_metrics as dm
from maem_ros.tools.demo.pose2sim_demo import fetch_demo


def frontend_detections(root: Path, rig: Rig, frames: int | None) -> list[dict]:
    """Per frame, {camera: FrameDetections} of the mediapipe frontend (rectified images)."""
    import cv2

    from maem_ros.frontend.base import make_estimator
    from maem_ros.frontend.rectify import Rectifier
    options = load_node_params("mediapipe.yaml", "frontend")
    ests = {c.name: make_estimator("mediapipe", options, rig) for c in rig}
    rects = {c.name: Rectifier(c) for c in rig}
    caps = {c.name: cv2.VideoCapture(str(root / "videos" / f"{c.name}.mp4")) for c in rig}
    fps = caps[rig.names[0]].get(cv2.CAP_PROP_FPS) or 60.0
    out: list[dict] = []
    while frames is None or len(out) < frames:
        images = {n: cap.read() for n, cap in caps.items()}
        if not all(ok for ok, _ in images.values()):
            break
        stamp = int(round(len(out) * 1e9 / fps))
        out.append({c.name: ests[c.name].estimate(c, stamp, rects[c.name].rectify(images[c.name][1]))
                    for c in rig})
    for cap in caps.values():
        cap.release()
    return out


def measure(rig: Rig, P_rig: np.ndarray, dets: dict, clusters: list, tri: TriangulationParams
            ) -> tuple[dm.MemberErrors, int, list[int]]:
    """(reprojection errors, people with a finite joint, members per cluster) of one frame."""
    rows = [(i, int(c), int(d)) for i, cl in enumerate(clusters) for c, d in cl.members]
    if not rows:
        return dm.MemberErrors(), 0, []
    which, cam, det = (np.array(x) for x in zip(*rows))
    kp = np.stack([dets[rig.names[c]].kpts2d[d] for c, d in zip(cam, det)])
    sc = np.array([dets[rig.names[c]].scores[d] for c, d in zip(cam, det)])
    poses, e = dm.member_reprojection_errors(P_rig, *pad_members(which, cam, kp, sc), tri)
    people = int(np.isfinite(np.asarray(poses.joints)).all(-1).any(-1).sum())
    return e, people, [len(cl.members) for cl in clusters]


def run(rig: Rig, seq: list[dict], assoc: AssociationParams, tri: TriangulationParams,
        temporal: TemporalParams | None) -> tuple[dict, list]:
    """Summary and per-frame (mean px, people, members) of one association over ``seq``."""
    P_rig = np.stack([c.P for c in rig])
    stage = TemporalAssociator(rig, assoc, temporal) if temporal is not None else None
    errs, frames = dm.MemberErrors(), []
    for dets in seq:
        stamp = next(iter(dets.values())).stamp_ns
        clusters = (stage.step(dets, stamp).clusters if stage is not None
                    else associate(rig, dets, assoc).clusters)
        e, people, members = measure(rig, P_rig, dets, clusters, tri)
        errs.add(e)
        kept = e.arrays()[0]
        frames.append((float(kept.mean()) if kept.size else float("nan"), people,
                       sorted(members, reverse=True)))
    summary = dm.reprojection_summary(errs, tri.tau_kps)
    summary["both_people"] = sum(f[1] >= 2 for f in frames)
    summary["exactly_two"] = sum(f[1] == 2 for f in frames)
    return summary, frames


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--verify", nargs="+", default=["association", "mesh"])
    a = ap.parse_args()
    root = fetch_demo()
    rig = Rig.load(root / "calibration" / "Calib.qca.txt")
    cache = a.out / "detections.pkl"
    if cache.is_file():
        seq = pickle.loads(cache.read_bytes())
    else:
        a.out.mkdir(parents=True, exist_ok=True)
        seq = frontend_detections(root, rig, a.frames)
        cache.write_bytes(pickle.dumps(seq))
    seq = seq[:a.frames] if a.frames else seq
    section = load_node_params("mediapipe.yaml", "association")
    assoc = AssociationParams.from_mapping(section)
    tri = TriangulationParams.from_mapping(load_node_params("mediapipe.yaml", "triangulation"))
    runs = {"per-frame (offline)": run(rig, seq, assoc, tri, None)}
    for mode in a.verify:
        tp = TemporalParams.from_mapping({**section, "verify_epipolar": mode})
        runs[f"tracks, verify_epipolar {mode}"] = run(rig, seq, assoc, tri, tp)
    print(f"{len(seq)} frames\n| association | reprojection mean / median px | joint-views | "
          f"members kept / rejected | frames >= 2 people (exactly 2) |\n|---|---|---|---|---|")
    for name, (s, _) in runs.items():
        print(f"| {name} | {s['reprojection_px_mean']:.2f} / {s['reprojection_px_median']:.2f} | "
              f"{s['reprojection_pairs']} | {s['reprojection_members'] - s['reprojection_members_rejected']}"
              f" / {s['reprojection_members_rejected']} | {s['both_people']} ({s['exactly_two']}) |")
    names = list(runs)
    ref = runs[names[0]][1]
    for name in names[1:]:
        diff = [(k, r, o) for k, (r, o) in enumerate(zip(ref, runs[name][1])) if r[1:] != o[1:]]
        print(f"\n{name}: {len(diff)} frames differ from per-frame (frame: per-frame px, people, "
              f"members | this)")
        for k, r, o in diff[:40]:
            print(f"  {k}: {r[0]:.1f} {r[1]} {r[2]} | {o[0]:.1f} {o[1]} {o[2]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
