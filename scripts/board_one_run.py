"""One-run board calibration (no --intrinsics) on rendered board sequences: per camera the focal,
principal-point and k1 errors, the reprojection median and the relative rotation error, for the
per-camera cv2.calibrateCamera intrinsics and for the joint bundle's.

    python scripts/board_one_run.py OUT_DIR [--rigs lab4 room6] [--seeds 1 2 3] [--frames 16]
        [--board charuco:7x5:0.15:0.11:DICT_4X4_50] [--modes per-camera joint6 joint8]

Sequences are rendered with maem-sim into OUT_DIR (kept for reruns) and detected once (the
detections cached next to them); modes: ``per-camera`` (the start), ``jointN`` (the bundle
refining fx fy cx cy k1 k2, and p1 p2 for N = 8). Rigs: maem-sim's (lab4 is the board rig), or
``room6`` (built here): 6 cameras of 1280x720 on a 4 m ring, f 820-960 px, k1 -0.08..-0.28.
"""
from __future__ import annotations

import argparse
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from maem_ros.core.calibrate.board import BoardSpec, NotSimultaneous, calibrate_extrinsics
from maem_ros.core.geometry.camera import Rig
from maem_ros.sim.rigs import _camera
from maem_ros.tools.calibrate.calibrate_board import detect_source, intrinsics_of

MODES = {"per-camera": (), "joint6": ("fx", "fy", "cx", "cy", "k1", "k2"),
         "joint8": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}


def room6() -> Rig:
    """6 cameras around a 4 m room volume, wider images and a spread of lenses (not lab4's)."""
    # (eye xyz, f px, k1, k2, p1, p2, roll rad, principal point shift px)
    spec = [((4.0, 0.3, 2.4), 900.0, -0.25, 0.08, 0.0005, -0.0004, 0.01, (8.0, -5.0)),
            ((2.1, 3.5, 1.6), 820.0, -0.08, 0.01, -0.0007, 0.0002, -0.02, (-6.0, 4.0)),
            ((-2.0, 3.4, 2.6), 960.0, -0.28, 0.10, 0.0002, 0.0006, 0.0, (2.0, 7.0)),
            ((-4.1, -0.2, 1.9), 870.0, -0.15, 0.03, 0.0009, -0.0002, 0.02, (-3.0, -2.0)),
            ((-1.9, -3.6, 2.2), 930.0, -0.22, 0.06, -0.0003, -0.0008, -0.015, (5.0, 3.0)),
            ((2.2, -3.3, 1.7), 840.0, -0.12, 0.02, 0.0004, 0.0005, 0.005, (-7.0, -6.0))]
    return Rig([_camera(f"cam{i}", eye, (0.0, 0.0, 1.0), (1280, 720), f, (k1, k2, p1, p2, 0.0),
                        roll, pp, aspect=0.997) for i, (eye, f, k1, k2, p1, p2, roll, pp)
                in enumerate(spec)])


def sequence(out: Path, rig: str, seed: int, frames: int, board: str) -> Path:
    seq = out / f"{rig}_s{seed}_f{frames}"
    if rig == "room6":
        out.mkdir(parents=True, exist_ok=True)
        room6().to_yaml(out / "room6.yaml")
        rig = str(out / "room6.yaml")
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
        try:
            ext = calibrate_extrinsics(spec, dets, [(intr[n].K, intr[n].D) for n in names], names,
                                       MODES[mode])
        except NotSimultaneous as e:  # the sequence's shared views do not connect the rig
            print(f"| {seq.name} | {mode} | FAILED: {e} |", flush=True)
            return
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
