"""How far a screening subset's mean epipolar distance is from the full-mesh mean.

For every candidate pair of the mesh gate (the pairs the bbox-centre reprojection gate keeps),
on maem-bench's loads and on simulated scenes, the exact float64 mean point-to-epipolar-line
distance over all vertices and over each screening subset (runs of 8 consecutive vertex ids,
one run in every 8 x stride: epipolar.screen_rows). Prints, per stride, the largest and p99
error against the full mean (all pairs, and pairs whose full mean is within 3 px of tau_mesh),
and, for the association's screening levels, the pairs each level decides and how many of its
decisions differ from the full mesh's.

    .venv/bin/python scripts/screen_study.py [--quick]

The numbers behind screen_margin and screen_coarse_margin (doc/design.md §9.3).
"""
from __future__ import annotations

import argparse
from collections.abc import Iterator

import numpy as np
from threadpoolctl import threadpool_limits

from maem_ros.core.association.gates import epipolar
from maem_ros.core.association.pipeline import AssociationParams, associate
from maem_ros.core.synthetic import body_template, make_frame
from maem_ros.params import load_node_params
from maem_ros.ros import wire
from maem_ros.sim.scene import Scene, SceneConfig
from maem_ros.tools.bench.bench_load import load_bench_rig

STRIDES = (64, 32, 16, 8, 4, 2)
NEAR_TAU = 3.0  # px


def bench_frames(rig_name: str, players: int, extras: int, seed: int, count: int) -> Iterator:
    """maem-bench's synthetic load (as decoded from f32 messages)."""
    rig = load_bench_rig(rig_name)
    rng = np.random.default_rng(seed)
    template = body_template(18439, 70, seed)
    for k in range(count):
        frame = make_frame(rig, template, rng, players, extras, stamp_ns=k)
        yield rig, {c: wire.msg_to_detections(wire.detections_to_msg(fd, "f32"), c)
                    for c, fd in frame.frames.items()}


def scene_frames(rig_name: str, difficulty: str, seed: int, count: int) -> Iterator:
    """Frames spread over a 90-frame simulated scene."""
    scene = Scene(SceneConfig(rig=rig_name, difficulty=difficulty, seed=seed, frames=90))
    for f in np.linspace(0, 89, count).astype(int).tolist():
        yield scene.rig, {c.name: scene.detections(c.name, f) for c in scene.rig.cameras}


def subset_mask(n: int, stride: int) -> np.ndarray:
    """The vertex ids epipolar.screen_rows keeps for this stride (n vertices), as a mask."""
    rows = epipolar.screen_rows(np.zeros((1, n, 2), np.float32), stride)
    mask = np.zeros(n, bool)
    mask[rows.positions(np.arange(rows.n))] = True
    return mask


def pair_means(full, F, cam_a, det_a, cam_b, det_b) -> np.ndarray:
    """(S, 1 + len(STRIDES)) float64 means: the full mesh, then each stride's subset."""
    n = next(iter(full.values())).n
    points = {c: np.stack([rows.points(i) for i in range(rows.count)]).astype(np.float64)
              for c, rows in full.items() if rows.count}
    masks = [subset_mask(n, s) for s in STRIDES]
    out = np.full((cam_a.size, 1 + len(STRIDES)), np.nan)
    F = epipolar.pair_matrices(F)
    for a, b in sorted(set(zip(cam_a.tolist(), cam_b.tolist()))):
        Fab = F.unit[F.lookup[a * F.cameras + b]].reshape(3, 3)
        pairs = np.flatnonzero((cam_a == a) & (cam_b == b))
        for chunk in np.array_split(pairs, max(1, pairs.size // 64)):
            d = epipolar.point_distances(points[a][det_a[chunk]], points[b][det_b[chunk]], Fab,
                                         True)
            with np.errstate(invalid="ignore"):
                out[chunk, 0] = np.nanmean(d, axis=1)
                for k, mask in enumerate(masks):
                    out[chunk, 1 + k] = np.nanmean(d[:, mask], axis=1)
    return out


def collect(sources: list[Iterator], params: AssociationParams) -> np.ndarray:
    """Means of every candidate pair of every frame set (captured from the association)."""
    captured, rows = [], []
    real = epipolar.frame_screened_means

    def capture(full, screens, F, cam_a, det_a, cam_b, det_b, *args, **kwargs):
        captured.append((full, F, cam_a.copy(), det_a.copy(), cam_b.copy(), det_b.copy()))
        return real(full, screens, F, cam_a, det_a, cam_b, det_b, *args, **kwargs)

    epipolar.frame_screened_means = capture
    try:
        for source in sources:
            for rig, frames in source:
                captured.clear()
                associate(rig, frames, params)
                rows += [pair_means(*c) for c in captured]
    finally:
        epipolar.frame_screened_means = real
    means = np.concatenate(rows)
    return means[np.isfinite(means).all(axis=1)]


def report(name: str, means: np.ndarray, params: AssociationParams) -> None:
    tau = params.tau_mesh
    full = means[:, 0]
    near = np.abs(full - tau) < NEAR_TAU
    print(f"{name}: {full.size} candidate pairs, {np.count_nonzero(full < tau)} pass on the "
          f"full mesh, {np.count_nonzero(near)} within {NEAR_TAU:g} px of tau_mesh")
    print("  stride  max|err|  p99    max|err| near tau  p99 near tau")
    for k, stride in enumerate(STRIDES):
        err = np.abs(means[:, 1 + k] - full)
        print(f"  {stride:6d}  {err.max():8.3f}  {np.percentile(err, 99):5.3f}  "
              f"{err[near].max():17.3f}  {np.percentile(err[near], 99):12.3f}")
    open_ = np.ones(full.size, bool)
    for stride, margin in params.screen_levels():
        m = means[:, 1 + STRIDES.index(stride)]
        accepted = open_ & (m < tau - margin)
        rejected = open_ & (m >= tau + margin)
        wrong = np.count_nonzero(accepted & (full >= tau)) + np.count_nonzero(
            rejected & (full < tau))
        near_err = np.abs(m - full)[open_ & (np.abs(full - tau) < margin + 1.0)]
        print(f"  level stride {stride} margin {margin:g} px: decides "
              f"{np.count_nonzero(accepted | rejected)} of {np.count_nonzero(open_)} open pairs, "
              f"{wrong} unlike the full mesh; largest error near its band / margin "
              f"{near_err.max(initial=0.0) / margin:.2f}")
        open_ &= ~(accepted | rejected)
    print(f"  full mesh decides the last {np.count_nonzero(open_)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames (a minute)")
    args = parser.parse_args(argv)
    params = AssociationParams.from_mapping(load_node_params("config/sportcenter.yaml",
                                                             "association"))
    k = 1 if args.quick else 2
    bench = ([bench_frames("ring16", 22, 3, s, k) for s in (0, 1)]
             + [bench_frames("sportcenter6", 10, 2, s, k + 1) for s in (0, 1)]
             + [bench_frames("ring16", 8, 6, 2, k)])
    scenes = [scene_frames(r, d, s, 3 * k) for r in ("sportcenter6", "humanm3_4")
              for d in ("medium", "hard") for s in (0, 1)]
    with threadpool_limits(1):
        report("maem-bench loads (ring16 22+3, sportcenter6 10+2, ring16 8+6)",
               collect(bench, params), params)
        report("simulated scenes (sportcenter6, humanm3_4; medium, hard)",
               collect(scenes, params), params)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
