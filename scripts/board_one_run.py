"""One-run board calibration (no --intrinsics) on rendered board sequences: per camera the focal,
principal-point and k1 errors, the reprojection median and the relative rotation error, for the
per-camera cv2.calibrateCamera intrinsics and for the joint bundle's.

    python scripts/board_one_run.py OUT_DIR [--rigs lab4] [--seeds 1 2 3] [--frames 16]
        [--board charuco:7x5:0.15:0.11:DICT_4X4_50] [--modes per-camera joint6 joint8]

Sequences are rendered with maem-sim into OUT_DIR (kept for reruns) and detected once (the
detections cached next to them); modes: ``per-camera`` (the start), ``jointN`` (the bundle
refining fx fy cx cy k1 k2, and p1 p2 for N = 8).
"""
from __future__ import annotations

import argparse
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from maem_ros.core.calibrate.board import BoardSpec, calibrate_extrinsics
from maem_ros.core.geometry.camera import Rig
from maem_ros.tools.calibrate.calibrate_board import detect_source, intrinsics_of

MODES = {"per-camera": (), "joint6": ("fx", "fy", "cx", "cy", "k1", "k2"),
         "joint8": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}


def sequence(out: Path, rig: str, seed: int, frames: int, board: str) -> Path:
    seq = out / f"{rig}_s{seed}_f{frames}"
    if not (seq / "gt_rig.yaml").is_file():
        subprocess.run([str(Path(sys.executable).parent / "maem-sim"), str(seq), "--rig", rig,
                        "--board", board, "--frames", str(frames), "--seed", str(seed), "--quiet"],
                       check=True, timeout=1800)
    return seq


def rotation_errors(truth: Rig, R: np.ndarray) -> np.ndarray:
    """Per camera the largest relative rotation error (deg) over its pairs."""
    C = len(truth)
    out = np.zeros(C)
    for a in range(C):
        for b in range(C):
            if a != b:
                E = (truth[b].R @ truth[a].R.T) @ (R[b] @ R[a].T).T
                out[a] = max(out[a], np.degrees(np.linalg.norm(Rotation.from_matrix(E).as_rotvec())))
    return out


def evaluate(seq: Path, spec: BoardSpec, modes: list[str]) -> None:
    cache = seq / "detections.pkl"
    if cache.is_file():
        frames = pickle.loads(cache.read_bytes())
    else:
        frames = detect_source(seq, spec)
        cache.write_bytes(pickle.dumps(frames))
    truth = Rig.load(seq / "gt_rig.yaml")
    intr = intrinsics_of(frames, spec, None)
    names = list(intr)
    dets = {(c, k): d for c, n in enumerate(names) for k, d in frames.detections[n].items()
            if d is not None}
    for mode in modes:
        ext = calibrate_extrinsics(spec, dets, [(intr[n].K, intr[n].D) for n in names], names,
                                   MODES[mode])
        rot = rotation_errors(truth, ext.R)
        for c, n in enumerate(names):
            t, K, D = truth[n], ext.K[c], ext.D[c]
            fe = 100 * (np.array([K[0, 0], K[1, 1]]) / [t.K[0, 0], t.K[1, 1]] - 1)
            pp = np.linalg.norm(K[:2, 2] - t.K[:2, 2])
            print(f"| {seq.name} | {mode} | {n} | {ext.frames_per_camera[c]} | {fe[0]:+.2f} / "
                  f"{fe[1]:+.2f} | {pp:.2f} | {D[0] - t.D[0]:+.4f} | "
                  f"{np.median(ext.errors[c]):.3f} | {rot[c]:.3f} |", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--rigs", nargs="+", default=["lab4"])
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--board", default="charuco:7x5:0.15:0.11:DICT_4X4_50")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    a = p.parse_args()
    spec = BoardSpec.parse(a.board)
    print("| sequence | mode | camera | frames | fx / fy err % | pp err px | k1 err | "
          "reproj median px | rel. rotation err deg |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for rig in a.rigs:
        for seed in a.seeds:
            evaluate(sequence(a.out, rig, seed, a.frames, a.board), spec, a.modes)


if __name__ == "__main__":
    main()
