"""Tracks on against tracks off on simulated scenes: recall, MPJPE, AP@100, the share of published
poses more than 200 mm from their person, and the calibration of the per-joint std.

    python scripts/precision_study.py OUT_DIR [--rigs humanm3_3 humanm3_4 sportcenter6]
        [--difficulties medium hard] [--seeds 1 2] [--frames 30]

Scenes are made with maem-sim (kept in OUT_DIR for reruns), evaluated with maem-eval --json
--pred with the rig's shipped params file; one table row per scene and setting, plus the
oracle row (maem-eval --oracle: the GT association, same triangulation; no far share or std
calibration, its poses are not written).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from maem_ros.core.interchange import SceneFolder
from maem_ros.core.metrics.poses import match_frame
from maem_ros.tools.eval.evaluate import load_gt

PARAMS = {"humanm3_3": "humanm3.yaml", "humanm3_4": "humanm3.yaml", "sportcenter6": "sportcenter.yaml"}


def far_share_and_calibration(scene: Path, pred: Path) -> tuple[float, float, float]:
    """% of published poses > 200 mm from their matched GT person (unmatched count as far), and
    the fractions of per-axis joint errors within 1 and 2 predicted std (matched poses)."""
    xyz, mask = load_gt(SceneFolder(scene))
    far = total = 0
    within1, within2, n = 0, 0, 0
    with np.load(pred) as z:
        pose, valid, std = z["pose"], z["valid"], z["joint_std"]
    for f in range(min(len(pose), len(xyz))):
        present = mask[f].any(-1)
        p = pose[f][valid[f]]
        s = std[f][valid[f]]
        r, c, cost = match_frame(p, xyz[f][present], mask[f][present])
        total += len(p)
        far += len(p) - int((cost <= 0.2).sum())
        err = np.abs(p[r] - xyz[f][present][c])  # (M,13,3)
        sd = s[r][..., None]
        ok = np.isfinite(err) & np.isfinite(sd) & mask[f][present][c][..., None]
        within1 += int((err <= sd)[ok].sum())
        within2 += int((err <= 2 * sd)[ok].sum())
        n += int(ok.sum())
    return 100.0 * far / max(total, 1), 100.0 * within1 / max(n, 1), 100.0 * within2 / max(n, 1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--rigs", nargs="+", default=list(PARAMS))
    ap.add_argument("--difficulties", nargs="+", default=["medium", "hard"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    bindir = Path(sys.executable).parent
    print("| scene | tracks | recall | MPJPE mean / median mm | AP@100 | poses > 200 mm % | "
          "within 1 / 2 std % |\n|---|---|---|---|---|---|---|", flush=True)
    for rig in args.rigs:
        for diff in args.difficulties:
            for seed in args.seeds:
                scene = args.out / f"{rig}-{diff}-{seed}"
                if not (scene / "gt.npz").is_file():
                    subprocess.run([bindir / "maem-sim", scene, "--rig", rig, "--frames",
                                    str(args.frames), "--difficulty", diff, "--seed", str(seed),
                                    "--quiet"], check=True)
                for temporal in ("on", "off"):
                    rep, pred = scene / f"eval_{temporal}.json", scene / f"pred_{temporal}.npz"
                    # the oracle (GT association, same triangulation) rides on the off run
                    subprocess.run([bindir / "maem-eval", scene, "--params", PARAMS[rig],
                                    "--temporal", temporal, "--quiet", "--json", rep, "--pred",
                                    pred] + (["--oracle"] if temporal == "off" else []),
                                   check=True, stdout=subprocess.DEVNULL)
                    m = json.loads(rep.read_text())
                    far, w1, w2 = far_share_and_calibration(scene, pred)
                    print(f"| {rig} {diff} s{seed} | {temporal} | {100 * m['recall']:.1f} | "
                          f"{m['mpjpe_mean']:.1f} / {m['mpjpe_median']:.1f} | "
                          f"{100 * m['ap100']:.1f} | {far:.1f} | {w1:.0f} / {w2:.0f} |", flush=True)
                    if "oracle" in m:
                        o = m["oracle"]
                        print(f"| {rig} {diff} s{seed} | oracle | {100 * o['recall']:.1f} | "
                              f"{o['mpjpe_mean']:.1f} / {o['mpjpe_median']:.1f} | "
                              f"{100 * o['ap100']:.1f} | - | - |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
