"""``maem-calib-bench``: people-mode calibration on simulated scenes against their true rigs.

Varies rigs (shipped court rigs and generated rings of cameras at several heights), number of
people, noise and seeds; simulates each scene (random per-camera capture offsets up to
+-50 ms on half of them), runs :func:`core.calibrate.people.calibrate_people` without and with
court points (the FIBA landmarks of config/court_points_fiba.yaml projected into the true
cameras, 1 px noise), and prints one row per run and a summary against issue 35's targets:

* relative rotation error of every camera pair (deg): median, max;
* camera centres after a similarity alignment, max, % of the rig's radius;
* up axis (deg): the world z of the calibrated rig against the true one;
* scale error (%) without and with court points;
* time offsets (ms): max error after removing the common part;
* run time (s) of the calibration (not of the simulation).

    maem-calib-bench [--frames 60] [--seeds 2] [--quick] [--large] [--only NAME]
                     [--time-method joint|gauss_seidel|gauss_seidel_partial]
                     [--time-test kernel|interpolated]

Timings depend on the machine's load; the brief's machine is shared.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from maem_ros.core.calibrate.court import CourtPoints
from maem_ros.core.calibrate.people import PeopleOptions, calibrate_people
from maem_ros.core.calibrate.people_data import people_data
from maem_ros.core.calibrate.timing_joint import TIME_METHODS, TIME_TESTS
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.geometry.procrustes import procrustes_align
from maem_ros.sim.rigs import look_at
from maem_ros.sim.scene import Scene, SceneConfig

COURT_FILE = Path(__file__).resolve().parents[3] / "config" / "court_points_fiba.yaml"


def ring_rig(n: int, radius: float, height: float, seed: int) -> Rig:
    """n 1920x1080 pinhole cameras (f 1100-1500 px) on a ring around the court, ``height`` m
    high (+-1 m), aimed near the centre."""
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + rng.uniform(-0.15, 0.15)
        eye = np.array([radius * 1.4 * np.cos(a), radius * np.sin(a), height + rng.uniform(-1, 1)])
        target = np.array([rng.uniform(-3, 3), rng.uniform(-2, 2), 0.5])
        R, t = look_at(eye, target, roll=rng.uniform(-0.03, 0.03))
        f = rng.uniform(1100, 1500)
        K = np.array([[f, 0, 959.5], [0, f, 539.5], [0, 0, 1]])
        cams.append(Camera(name=f"cam{i}", K=K, R=R, t=t, width=1920, height=1080))
    return Rig(cams)


def court_points(rig: Rig, rng: np.random.Generator) -> CourtPoints:
    data = yaml.safe_load(COURT_FILE.read_text())
    names = list(data["landmarks"])
    court = np.array([data["landmarks"][n] for n in names], float)
    pixels = {}
    for cam in rig:
        uv = cam.project(court)
        inside = (
            np.all(np.isfinite(uv), 1)
            & (uv[:, 0] > 0)
            & (uv[:, 0] < cam.width)
            & (uv[:, 1] > 0)
            & (uv[:, 1] < cam.height)
        )
        pixels[cam.name] = {int(i): uv[i] + rng.normal(0, 1.0, 2) for i in np.flatnonzero(inside)}
    return CourtPoints(names, court, pixels)


def metrics(est: Rig, true: Rig, truth_offsets: dict) -> dict:
    names = [n for n in true.names if n in est]
    rot = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            Re, Rt = est[a].R @ est[b].R.T, true[a].R @ true[b].R.T
            rot.append(np.degrees(np.arccos(np.clip((np.trace(Re @ Rt.T) - 1) / 2, -1, 1))))
    A = np.stack([est[n].center for n in names])
    B = np.stack([true[n].center for n in names])
    aligned, s, _, _ = procrustes_align(A[None], B[None])
    radius = np.max(np.linalg.norm(B - B.mean(0), axis=1))
    up = [np.degrees(np.arccos(np.clip(est[n].R[:, 2] @ true[n].R[:, 2], -1, 1))) for n in names]
    off = np.array([est[n].time_offset - truth_offsets.get(n, 0.0) for n in names])
    off -= np.median(off)
    return {
        "rot_med": float(np.median(rot)),
        "rot_max": float(np.max(rot)),
        "centre_pct": float(100 * np.max(np.linalg.norm(aligned[0] - B, axis=1)) / radius),
        "up": float(np.median(up)),
        "scale_pct": float(100 * abs(1 / s[0] - 1)),
        "offset_ms": float(1000 * np.max(np.abs(off))),
        "calibrated": len(names),
        "cameras": len(true),
    }


def scenarios(
    quick: bool, large: bool, seeds: int
) -> Iterator[tuple[str, tuple[int, float, float] | None, int, str, int, bool]]:
    rigs: list[tuple[str, tuple[int, float, float] | None]] = [
        ("sportcenter6", None),
        ("humanm3_4", None),
        ("ring8_h3", (8, 14.0, 3.0)),
        ("ring8_h8", (8, 14.0, 8.0)),
        ("ring5_h5", (5, 12.0, 5.0)),
    ]
    if quick:
        rigs = rigs[:1] + rigs[3:4]
    for seed in range(seeds):
        for k, (name, ring) in enumerate(rigs):
            players = (10, 20)[(k + seed) % 2]
            difficulty = ("easy", "medium")[(k + seed + 1) % 2]
            yield name, ring, players, difficulty, seed, bool((k + seed) % 2)
    if large:
        yield "ring8_h6_large", (8, 14.0, 6.0), 20, "medium", 0, False


def run_one(
    name: str,
    ring: tuple[int, float, float] | None,
    players: int,
    difficulty: str,
    seed: int,
    offsets_on: bool,
    frames: int,
    tmp: Path,
    time_method: str = "gauss_seidel",
    time_test: str = "kernel",
) -> dict:
    rng = np.random.default_rng(100 + seed)
    rig_arg = name
    if ring is not None:
        path = tmp / f"{name}_{seed}.yaml"
        ring_rig(ring[0], ring[1], ring[2], seed=seed).to_yaml(path)
        rig_arg = str(path)
    cfg = SceneConfig(
        rig=rig_arg,
        frames=frames,
        difficulty=difficulty,
        players=players,
        bystanders=2,
        num_vertices=19,
        seed=seed,
    )
    true_rig = Scene(cfg).rig
    offsets = {
        c: float(rng.uniform(-0.05, 0.05)) for c in true_rig.names[1:] if offsets_on and rng.random() < 0.6
    }
    cfg.time_offsets = offsets
    scene = Scene(cfg)
    dets = {c.name: [scene.detections(c.name, f) for f in range(frames)] for c in scene.rig}
    intr = Rig([c for c in scene.rig])
    row: dict = {"scene": f"{name} s{seed} {players}p {difficulty}" + (" offs" if offsets else "")}
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate_people(
        people_data(intr, dets, cfg.fps),
        PeopleOptions(seed=seed, time_method=time_method, time_test=time_test),
    )
    row["time_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.process_time() - c0  # this process's CPU time: load-independent
    row.update(metrics(res.rig, scene.rig, offsets))
    res_c = calibrate_people(
        people_data(intr, dets, cfg.fps),
        PeopleOptions(seed=seed, court=court_points(scene.rig, rng), estimate_time=False),
    )
    row["scale_court_pct"] = metrics(res_c.rig, scene.rig, {})["scale_pct"]
    row["warnings"] = len(res.warnings)
    return row


COLUMNS = (
    ("scene", "{:<34}"),
    ("cameras", "{:>4}"),
    ("calibrated", "{:>4}"),
    ("rot_med", "{:>8.3f}"),
    ("rot_max", "{:>8.3f}"),
    ("centre_pct", "{:>8.2f}"),
    ("up", "{:>7.2f}"),
    ("scale_pct", "{:>8.2f}"),
    ("scale_court_pct", "{:>8.2f}"),
    ("offset_ms", "{:>8.1f}"),
    ("time_s", "{:>8.1f}"),
    ("cpu_s", "{:>8.1f}"),
)
HEADER = (
    f"{'scene':<34}{'cams':>4}{'ok':>4}{'rot med':>8}{'rot max':>8}{'ctr %R':>8}{'up deg':>7}"
    f"{'scale%':>8}{'court%':>8}{'offs ms':>8}{'time s':>8}{'cpu s':>8}"
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="maem-calib-bench", description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="two rigs per seed")
    ap.add_argument("--only", default=None, help="only the scenes whose rig name contains this")
    ap.add_argument(
        "--large",
        action="store_true",
        help="also the timing target's scene: 8 cameras x 20 people x --frames",
    )
    ap.add_argument(
        "--time-method",
        choices=TIME_METHODS,
        default=PeopleOptions.time_method,
        help="time-offset estimator (PeopleOptions.time_method)",
    )
    ap.add_argument(
        "--time-test",
        choices=TIME_TESTS,
        default=PeopleOptions.time_test,
        help="joint significance test of the offsets (PeopleOptions.time_test)",
    )
    args = ap.parse_args(argv)
    rows = []
    print(HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for sc in scenarios(args.quick, args.large, args.seeds):
            if args.only and args.only not in sc[0]:
                continue
            try:
                row = run_one(
                    *sc,
                    frames=args.frames,
                    tmp=Path(tmp),
                    time_method=args.time_method,
                    time_test=args.time_test,
                )
            except ValueError as e:
                print(f"{sc[0]} seed {sc[4]}: FAILED: {e}")
                continue
            rows.append(row)
            print("".join(fmt.format(row[k]) for k, fmt in COLUMNS), flush=True)
    if not rows:
        return 1
    col = {k: np.array([r[k] for r in rows]) for k, _ in COLUMNS[3:]}
    print(f"\nover {len(rows)} runs (targets in brackets):")
    print(
        f"  relative rotation: median of medians {np.median(col['rot_med']):.3f} deg [<= 0.5], "
        f"worst max {col['rot_max'].max():.3f} deg [<= 1]"
    )
    print(f"  centres: worst {col['centre_pct'].max():.2f} % of the rig radius [<= 2]")
    print(f"  up axis: worst {col['up'].max():.2f} deg [<= 1]")
    print(
        f"  scale: worst {col['scale_pct'].max():.1f} % without court points [<= 10], "
        f"{col['scale_court_pct'].max():.2f} % with [<= 1]"
    )
    print(f"  time offsets: worst {col['offset_ms'].max():.1f} ms [<= 4 with offsets, <= 8 in sync]")
    print(
        f"  run time: median {np.median(col['time_s']):.1f} s wall / {np.median(col['cpu_s']):.1f} s "
        f"CPU, max {col['time_s'].max():.1f} s wall / {col['cpu_s'].max():.1f} s CPU (shared machine)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
