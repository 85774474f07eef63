"""Calibration of the per-joint std (core/triangulation/uncertainty.py) on simulated scenes.

    python scripts/uncertainty_calibration.py SCENE_DIR... [--temporal on|off]
        [--set noise_prior_px=3 ...]

Each scene (a maem-sim folder, e.g. the ones scripts/precision_study.py makes) is associated
once with its rig's shipped params (config/humanm3.yaml, config/sportcenter.yaml by name, as
maem-eval) and the clusters are cached (SCENE/clusters_<temporal>.pkl); then triangulated with
the params (plus ``--set`` overrides of the triangulation section) and scored against gt.npz:
for every joint of a published pose matched to a GT person (core.metrics.poses.match_frame),
the per-axis error |e_x|, |e_y|, |e_z| against the published std (sqrt(trace(cov) / 3), the
RMS over the world axes): within 1 / 2 std (a Gaussian per axis: 68.3 / 95.4 %), and the RMS of
|e| / sqrt(trace(cov)) (1 when the covariance's scale is right). Rows: the triangulation as is
(``raw``) and after the joint filter (``published``, what /maem/poses and maem-eval --pred
carry).
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np
import yaml
from scipy.special import erf
from scipy.stats import chi2

from maem_ros.core.interchange import SceneFolder
from maem_ros.core.metrics.poses import match_frame
from maem_ros.core.tracking.joint_filter import filter_and_score
from maem_ros.core.triangulation.ransac import TriangulationParams, triangulate
from maem_ros.params import load_node_params
from maem_ros.tools.eval.evaluate import (
    SkipLog,
    load_frame,
    load_gt,
    load_params,
    make_joint_filter,
    make_tracker,
    to_sportcenter13,
)

PARAMS = {"humanm3": "humanm3.yaml", "sportcenter": "sportcenter.yaml"}


def params_of(scene: Path) -> str:
    """The shipped params file of the scene's rig (by the rig's name in the folder name)."""
    return next(v for k, v in PARAMS.items() if k in scene.name)


def clusters(scene: Path, temporal: str) -> list:
    """Per frame (frames, clusters, track ids or None, stamp), cached in the scene folder."""
    cache = scene / f"clusters_{temporal}.pkl"
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    folder = SceneFolder(scene)
    assoc, _ = load_params(params_of(scene))
    tracker = make_tracker(folder.rig, assoc, params_of(scene), temporal)
    gt = load_gt(folder)
    assert gt is not None, f"{scene}: no gt.npz"
    out = []
    skips = SkipLog()
    for f in range(gt[0].shape[0]):
        frames = load_frame(folder, folder.views, f, skips)
        stamp = min(fd.stamp_ns for fd in frames.values())
        if temporal == "on":
            step = tracker.step(frames, stamp)
            out.append((frames, step.clusters, np.asarray(step.track_ids), stamp))
        else:
            from maem_ros.core.association.pipeline import associate
            out.append((frames, associate(folder.rig, frames, assoc).clusters, None, stamp))
    cache.write_bytes(pickle.dumps(out))
    return out


def normalized_errors(scene: Path, seq: list, tri: TriangulationParams, temporal: str
                      ) -> dict[str, np.ndarray]:
    """Per row (raw / published), (N,9): per-axis |e| / std (3 columns), |e| / sqrt(trace cov);
    raw only (else NaN): the model's probability of each axis within 1 std (3), of within 2 std
    (mean over axes), the Mahalanobis distance^2 of e under cov."""
    folder = SceneFolder(scene)
    xyz, mask = load_gt(folder)
    jf = make_joint_filter(params_of(scene))
    post = make_tracker(folder.rig, load_params(params_of(scene))[0], params_of(scene), "off")
    rows: dict[str, list] = {"raw": [], "published": []}
    for f, (frames, cl, ids, stamp) in enumerate(seq):
        poses = triangulate(folder.rig, frames, cl, tri)
        n = len(poses)
        if not n:
            continue
        joints = to_sportcenter13(np.asarray(poses.joints, np.float64))
        cov = to_sportcenter13(np.asarray(poses.joint_cov).reshape(n, -1, 9)).reshape(n, -1, 3, 3)
        ids = post.update(stamp, joints) if ids is None else ids
        pub, std_pub, _ = filter_and_score(stamp, np.asarray(ids, np.int64), joints, cov,
                                           np.asarray(poses.detection_scores), jf,
                                           tri.pose_score, tri.score_ref_m)
        std_raw = np.sqrt(np.trace(cov, axis1=-2, axis2=-1) / 3.0)
        present = mask[f].any(-1)
        for name, p, s in (("raw", joints, std_raw), ("published", pub, std_pub)):
            valid = np.isfinite(p).all(-1).any(-1)
            p, s = p[valid], s[valid]
            r, c, _ = match_frame(p, xyz[f][present], mask[f][present])
            e = p[r] - xyz[f][present][c]
            sd = s[r]
            ok = np.isfinite(e).all(-1) & np.isfinite(sd) & mask[f][present][c]
            ax = np.abs(e[ok]) / sd[ok][:, None]
            rad = np.linalg.norm(e[ok], axis=-1) / (np.sqrt(3.0) * sd[ok])
            extra = np.full((len(ax), 5), np.nan)
            if name == "raw":  # the model's own expectation of the per-axis fractions
                C = cov[valid][r][ok]  # (N,3,3)
                sig = np.sqrt(np.diagonal(C, axis1=-2, axis2=-1))  # (N,3) per-axis std, m
                extra[:, :3] = erf(sd[ok][:, None] / (np.sqrt(2.0) * sig))
                extra[:, 3] = (erf(2.0 * sd[ok][:, None] / (np.sqrt(2.0) * sig))).mean(1)
                d = e[ok]
                extra[:, 4] = np.einsum("ni,nij,nj->n", d, np.linalg.inv(C), d)  # Mahalanobis^2
            rows[name].append(np.concatenate([ax, rad[:, None], extra], axis=1))
    return {k: np.concatenate(v) if v else np.zeros((0, 9)) for k, v in rows.items()}


def row(scene: str, name: str, z: np.ndarray) -> str:
    """One table row of normalized errors z (N,9) (normalized_errors)."""
    model = (f"{100 * np.nanmean(z[:, 4:7]):.1f} / {100 * np.nanmean(z[:, 7]):.1f}"
             if np.isfinite(z[:, 4]).any() else "-")
    maha = (f"{100 * (z[:, 8] <= chi2.ppf(0.683, 3)).mean():.1f} / "
            f"{100 * (z[:, 8] <= chi2.ppf(0.954, 3)).mean():.1f}"
            if np.isfinite(z[:, 8]).any() else "-")
    return (f"| {scene} | {name} | {100 * (z[:, :3] <= 1).mean():.1f} / "
            f"{100 * (z[:, :3] <= 2).mean():.1f} | {model} | {maha} | "
            f"{np.sqrt((z[:, 3] ** 2).mean()):.2f} | {len(z)} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--temporal", choices=("on", "off"), default="on")
    ap.add_argument("--set", nargs="*", default=[], help="triangulation overrides KEY=VALUE")
    a = ap.parse_args()
    print("| scene | row | within 1 / 2 std per axis % | the model's expectation of the same % | "
          "Mahalanobis within the chi2(3) 68.3 / 95.4 % quantiles % | "
          "RMS of abs(e) / sqrt(trace cov) | joints |\n|---|---|---|---|---|---|---|")
    total: dict[str, list] = {"raw": [], "published": []}
    for scene in a.scenes:
        section = dict(load_node_params(params_of(scene), "triangulation"))
        section.update({k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)})
        tri = TriangulationParams.from_mapping(section)
        res = normalized_errors(scene, clusters(scene, a.temporal), tri, a.temporal)
        for name, z in res.items():
            total[name].append(z)
            print(row(scene.name, name, z), flush=True)
    for name, zs in total.items():
        print(row("all", name, np.concatenate(zs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
