"""maem-bench: time MAEM association and triangulation on the standard load, one CPU thread.

Standard load (core/synthetic.py): 6 cameras (shipped ``sportcenter6`` rig, plumb_bob distortion),
12 detections per camera (10 players seen by every camera + 2 extra people per camera), 70
keypoints, 18,439 mesh vertices, geometry consistent through the rig, 0.5 px pixel noise, fixed
seed. ``--load large``: 16 cameras on a ring around the court (``ring16``), 25 detections per camera
(22 players seen by every camera + 3 extras per camera), full mesh. Times the full association (all
stages) and the triangulation per frame (median, p90), and in the same run a straightforward
association written the way the method reads (loops over detection pairs, per-pair OpenCV
undistortion of the raw vertex pixels, per-pair distances), and checks both give identical clusters.

    maem-bench                 # human-readable summary
    maem-bench --load large    # 16 cameras x 25 detections
    maem-bench --json          # one JSON object
    maem-bench --vertices 500 --frames 1 --repeats 1 --json   # quick smoke run
    maem-bench --live [--wire q4] [--bag BAG]   # camera-rate run through the node graph
                                                # (tools/bench/live.py)

Temporal on/off (same run): the load in motion (core/synthetic.make_sequence: the same people
walking at 1.5 m/s, ``--temporal-frames`` frames at 30 fps) through core.tracking.temporal's
track-assisted association and through the per-frame association; per-frame times after the
first frame (steady state: tracks explain the known people, cross-view association runs on the
rest), the first frame apart, and the detections left to the cross-view stage; each frame
decoded from its messages as the node decodes them (not timed).

Targets (reported, not enforced): standard load association median <= 6.5 ms/frame,
triangulation median <= 1.5 ms for 10 people, speedup >= 50; large load association median
<= 33 ms. Timings on a shared machine are noisy: ``min`` beside the median says how much.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

from maem_ros.tools.cli import fail

#: thread pools pinned to one thread; must be set before numpy/OpenCV/numba load
_THREAD_ENV = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMBA_NUM_THREADS",
)

#: the loads: rig, people seen by every camera, extra people per camera
LOADS = {"standard": ("sportcenter6", 10, 2), "large": ("ring16", 22, 3)}
TARGETS = {
    "standard": {"association_ms_median": 6.5, "speedup": 50.0, "triangulation_ms_median": 1.5},
    "large": {"association_ms_median": 33.0},
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-bench",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Targets (reported only): association median <= 6.5 ms "
        "(--load large: <= 33 ms), speedup >= 50, "
        "triangulation median <= 1.5 ms.",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--load",
        default="standard",
        choices=sorted(LOADS),
        help="standard (6 cameras x 12) or large (16 cameras x 25); sets the rig, "
        "--players and --extras unless given",
    )
    p.add_argument("--rig", default=None, help="rig name or file (default: the load's)")
    p.add_argument(
        "--params",
        default=None,
        help="params file for the association/triangulation thresholds (default "
        "sportcenter.yaml; --live: demo.yaml, whose synthetic scene it plays)",
    )
    p.add_argument("--vertices", type=int, default=18439, help="mesh vertices per detection")
    p.add_argument("--keypoints", type=int, default=70, help="keypoints per detection")
    p.add_argument(
        "--players", type=int, default=None, help="people seen by every camera (default: the load's, 10 / 22)"
    )
    p.add_argument(
        "--extras",
        type=int,
        default=None,
        help="extra people per camera, seen by that camera only (default 2 / 3)",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="distinct frames in the load (default 5; --live: frames published, 90)",
    )
    p.add_argument("--repeats", type=int, default=10, help="timed runs per frame (fast paths)")
    p.add_argument(
        "--straightforward-frames",
        type=int,
        default=None,
        help="frames the straightforward implementation runs on (slow; default 2, large load 1)",
    )
    p.add_argument(
        "--wire",
        default="f32",
        choices=("f32", "q4"),
        help="detections layout the load is decoded from (as the node receives it)",
    )
    p.add_argument(
        "--backend",
        default="auto",
        choices=("auto", "numba", "numpy"),
        help="epipolar kernel of the fast path",
    )
    p.add_argument(
        "--temporal-frames",
        type=int,
        default=30,
        help="frames of the temporal on/off comparison (0 = skip it)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--dump",
        default=None,
        metavar="PATH",
        help="write every frame's clusters (members, costs as exact hex floats) of "
        "the fast path, the paper pipeline and the temporal run to PATH (JSON), "
        "to compare two versions' decisions",
    )
    from .live import add_live_arguments

    add_live_arguments(p)
    return p


def _load_defaults(args: argparse.Namespace) -> argparse.Namespace:
    args.params = args.params or ("demo.yaml" if args.live else "sportcenter.yaml")
    args.frames = args.frames if args.frames is not None else (90 if args.live else 5)
    rig, players, extras = LOADS[args.load]
    args.rig = args.rig or rig
    args.players = players if args.players is None else args.players
    args.extras = extras if args.extras is None else args.extras
    if args.straightforward_frames is None:
        args.straightforward_frames = 1 if args.load == "large" else 2
    return args


def _pin_threads() -> None:
    for var in _THREAD_ENV:
        os.environ[var] = "1"


def _percentile(values, q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else float("nan")


def run(args: argparse.Namespace) -> dict:
    """Build the load, time both paths, return the result dict."""

    import cv2
    import numpy as np
    from threadpoolctl import threadpool_limits

    from maem_ros.core.association import AssociationParams
    from maem_ros.core.synthetic import body_template, make_frame
    from maem_ros.core.triangulation.ransac import TriangulationParams
    from maem_ros.params import load_node_params

    from .bench_load import load_bench_rig

    for name in ("vertices", "keypoints", "players", "frames", "repeats"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: must be >= 1, got {getattr(args, name)}")
    if args.extras < 0 or args.straightforward_frames < 0 or args.temporal_frames < 0:
        raise ValueError("--extras/--straightforward-frames/--temporal-frames: must be >= 0")
    cv2.setNumThreads(1)
    with threadpool_limits(limits=1):
        rig = load_bench_rig(args.rig)
        aparams = AssociationParams.from_mapping(
            {**load_node_params(args.params, "association"), "backend": args.backend}
        )
        tparams = TriangulationParams.from_mapping(load_node_params(args.params, "triangulation"))
        rng = np.random.default_rng(args.seed)
        template = body_template(args.vertices, args.keypoints, args.seed)
        load = [
            make_frame(rig, template, rng, args.players, args.extras, stamp_ns=k) for k in range(args.frames)
        ]
        timed = _time_node_path(args, rig, load, aparams, tparams)
        paper = _paper_vs_straightforward(args, rig, load, aparams)
    out = _summary(args, rig, load, aparams, timed, paper)
    dump = {
        "association": [_cluster_rows(res.clusters) for res, _ in timed["results"]],
        "paper": paper["dump"],
    }
    if args.temporal_frames:
        with threadpool_limits(limits=1):
            out["temporal"] = _temporal(args, rig, aparams, template, dump)
    if args.dump:
        with open(args.dump, "w", encoding="utf-8") as f:
            json.dump(dump, f)
    return out


def _time_node_path(args: argparse.Namespace, rig, load, aparams, tparams) -> dict:
    """The node path on every frame, ``args.repeats`` times: decode + validate each camera's
    message (f32: views of msg.data), prepare it for the pair gates, associate, triangulate.
    Per-run wall and CPU times (CPU time beside wall time: on a shared machine the wall time
    also counts the time other processes held the core), stage times, the last results."""
    from maem_ros.core.association import PairGates, associate
    from maem_ros.core.triangulation.ransac import triangulate
    from maem_ros.ros import wire

    t0 = time.perf_counter()
    gates = PairGates(rig, aparams)
    associate(
        rig, {c: gates.prepare(fd) for c, fd in load[0].frames.items()}, aparams, gates
    )  # warm-up: JIT load/compile, caches
    timed: dict = {"warmup_ms": (time.perf_counter() - t0) * 1e3, "stages": {}, "results": []}
    for key in ("assoc", "assoc_cpu", "tri", "tri_cpu", "decode"):
        timed[key] = []
    for fr in load:
        msgs = {c: wire.detections_to_msg(fd, args.wire) for c, fd in fr.frames.items()}
        for _ in range(args.repeats):
            t = time.perf_counter()
            frames = {
                c: gates.prepare(wire.msg_to_detections(m, f"/{c}/detections")) for c, m in msgs.items()
            }
            timed["decode"].append((time.perf_counter() - t) * 1e3)
            c = time.process_time()
            res = associate(rig, frames, aparams, gates)
            timed["assoc_cpu"].append((time.process_time() - c) * 1e3)
            t, c = time.perf_counter(), time.process_time()
            poses = triangulate(rig, frames, res.clusters, tparams)
            timed["tri"].append((time.perf_counter() - t) * 1e3)
            timed["tri_cpu"].append((time.process_time() - c) * 1e3)
            timed["assoc"].append(res.stats["t_total_ms"])
            for k, v in res.stats.items():
                if k.startswith("t_"):
                    timed["stages"].setdefault(k, []).append(v)
        timed["results"].append((res, poses))
    return timed


def _paper_vs_straightforward(args: argparse.Namespace, rig, load, aparams) -> dict:
    """The paper's pipeline, fast path against the straightforward implementation (the
    straightforward implementation is the paper's pipeline: like with like)."""
    from maem_ros.core.association import PAPER_PIPELINE, associate

    from .bench_load import straightforward_associate

    paper = aparams.replaced(PAPER_PIPELINE)
    out: dict = {"straight": [], "fast": [], "identical": True, "dump": []}
    for fr in load[: args.straightforward_frames]:
        t = time.perf_counter()
        ref = straightforward_associate(rig, fr.raw, paper)
        out["straight"].append((time.perf_counter() - t) * 1e3)
        fast = [associate(rig, fr.frames, paper) for _ in range(args.repeats)]
        out["fast"].extend(r.stats["t_total_ms"] for r in fast)
        out["identical"] &= _as_sets(ref) == _as_sets([c.members for c in fast[0].clusters])
        out["dump"].append(_cluster_rows(fast[0].clusters))
    return out


def _summary(args: argparse.Namespace, rig, load, aparams, timed: dict, paper: dict) -> dict:
    """The result dict of the timed runs."""
    import numpy as np

    from maem_ros.ros import wire

    results, straight_ms = timed["results"], paper["straight"]
    recovered = sum(
        len(set(fr.truth) & set(_as_sets([c.members for c in res.clusters])))
        for fr, (res, _) in zip(load, results)
    )
    straight_med, paper_med = _percentile(straight_ms, 50), _percentile(paper["fast"], 50)
    out = {
        "cameras": len(rig),
        "detections_per_camera": args.players + args.extras,
        "vertices": args.vertices,
        "keypoints": args.keypoints,
        "people_per_frame": args.players,
        "frames": args.frames,
        "repeats": args.repeats,
        "threads": 1,
        "backend": args.backend,
        "rig": args.rig,
        "seed": args.seed,
        "clustering": aparams.clustering,
        "load": args.load,
        "association_ms_median": _percentile(timed["assoc"], 50),
        "association_ms_min": min(timed["assoc"]),
        "association_ms_p90": _percentile(timed["assoc"], 90),
        "association_cpu_ms_median": _percentile(timed["assoc_cpu"], 50),
        "association_cpu_ms_min": min(timed["assoc_cpu"]),
        "triangulation_ms_median": _percentile(timed["tri"], 50),
        "triangulation_ms_min": min(timed["tri"]),
        "triangulation_cpu_ms_median": _percentile(timed["tri_cpu"], 50),
        "triangulation_cpu_ms_min": min(timed["tri_cpu"]),
        "load_average_1min": os.getloadavg()[0],
        "wire": args.wire,
        "wire_decode_ms_median": _percentile(timed["decode"], 50),
        "wire_bytes_per_camera": int(
            np.median([len(wire.detections_to_msg(fd, args.wire).data) for fd in load[0].frames.values()])
        ),
        "triangulation_ms_p90": _percentile(timed["tri"], 90),
        "paper_association_ms_median": paper_med,
        "straightforward_association_ms_median": straight_med,
        "straightforward_frames": len(straight_ms),
        "speedup": straight_med / paper_med if straight_ms else float("nan"),
        "clusters_identical": bool(paper["identical"]) if straight_ms else None,
        "true_clusters_recovered": recovered,
        "true_clusters": args.players * args.frames,
        "triangulated_people_median": _percentile([len(p) for _, p in results], 50),
        "warmup_ms": timed["warmup_ms"],
        "stage_ms_median": {k[2:-3]: _percentile(v, 50) for k, v in timed["stages"].items()},
    }
    out["targets"] = {
        k: {"target": v, "met": bool(out[k] >= v if k == "speedup" else out[k] <= v)}
        for k, v in TARGETS[args.load].items()
    }
    return out


def _cluster_rows(clusters, track_ids=None) -> list:
    """Clusters as JSON rows: [members [[camera, detection], ...], costs as hex floats (exact,
    NaN included)] (and the track id when given)."""
    rows = [[c.members.tolist(), [float(v).hex() for v in c.costs]] for c in clusters]
    if track_ids is not None:
        rows = [r + [int(t)] for r, t in zip(rows, track_ids)]
    return rows


def _temporal(args: argparse.Namespace, rig, aparams, template, dump: dict) -> dict:
    """Temporal on vs off on the load in motion (module docstring)."""
    import numpy as np

    from maem_ros.core.association import associate
    from maem_ros.core.synthetic import make_sequence
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    from maem_ros.ros import wire

    seq = make_sequence(
        rig, template, np.random.default_rng(args.seed + 1), args.players, args.extras, args.temporal_frames
    )
    on: list[float] = []
    off: list[float] = []
    first: list[float] = []
    left: list[float] = []
    dump["temporal"] = []
    for _ in range(max(1, args.repeats // 5)):  # whole sequences: the tracker is stateful
        stage = TemporalAssociator(rig, aparams, TemporalParams())
        for f, fr in enumerate(seq):
            # decoded as the node receives them (not timed: the node decodes each message
            # as it arrives)
            frames = {
                c: stage.gates.prepare(
                    wire.msg_to_detections(wire.detections_to_msg(fd, args.wire), f"/{c}/detections")
                )
                for c, fd in fr.frames.items()
            }
            t = time.perf_counter()
            res = stage.step(frames, frames[rig.names[0]].stamp_ns)
            ms = (time.perf_counter() - t) * 1e3
            (first if f == 0 else on).append(ms)
            if f:
                left.append(res.stats["detections_left"])
            dump["temporal"].append(_cluster_rows(res.clusters, res.track_ids))
            t = time.perf_counter()
            associate(rig, frames, aparams, stage.gates)
            off.append((time.perf_counter() - t) * 1e3)
    found = len(set(seq[-1].truth) & set(_as_sets([c.members for c in res.clusters])))
    on_med, off_med = _percentile(on, 50), _percentile(off, 50)
    return {
        "frames": len(seq),
        "on_ms_median": on_med,
        "on_ms_p90": _percentile(on, 90),
        "on_first_frame_ms_median": _percentile(first, 50),
        "off_ms_median": off_med,
        "off_ms_p90": _percentile(off, 90),
        "off_over_on": off_med / on_med,
        "detections_left_median": _percentile(left, 50),
        "detections_per_frame": len(rig) * (args.players + args.extras),
        "true_clusters_last_frame": found,
        "players": args.players,
    }


def _finite_or_null(x):
    """NaN/inf -> null so --json output is strict JSON."""
    if isinstance(x, dict):
        return {k: _finite_or_null(v) for k, v in x.items()}
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _as_sets(clusters) -> list[frozenset]:
    return [frozenset(map(tuple, m.tolist())) for m in clusters]


def _print_human(r: dict) -> None:
    print(
        f"load {r['load']}: {r['cameras']} cameras x {r['detections_per_camera']} detections, "
        f"{r['keypoints']} keypoints, {r['vertices']} vertices; {r['frames']} frames x "
        f"{r['repeats']} repeats, 1 thread, backend {r['backend']}"
    )
    print(
        f"association     median {r['association_ms_median']:8.2f} ms   "
        f"p90 {r['association_ms_p90']:8.2f} ms   min {r['association_ms_min']:8.2f} ms   "
        f"(CPU median {r['association_cpu_ms_median']:.2f}, min "
        f"{r['association_cpu_ms_min']:.2f} ms; load average {r['load_average_1min']:.1f})"
    )
    stages = ", ".join(f"{k} {v:.2f}" for k, v in r["stage_ms_median"].items())
    print(f"  stages (median ms): {stages}")
    print(
        f"wire decode ({r['wire']}, all cameras) median {r['wire_decode_ms_median']:.2f} ms, "
        f"{r['wire_bytes_per_camera'] / 1e6:.2f} MB per camera message"
    )
    print(
        f"triangulation   median {r['triangulation_ms_median']:8.2f} ms   "
        f"p90 {r['triangulation_ms_p90']:8.2f} ms   min {r['triangulation_ms_min']:8.2f} ms   "
        f"(CPU median {r['triangulation_cpu_ms_median']:.2f}, min "
        f"{r['triangulation_cpu_ms_min']:.2f} ms)"
    )
    print(
        f"paper pipeline  median {r['paper_association_ms_median']:8.2f} ms; straightforward "
        f"median {r['straightforward_association_ms_median']:8.1f} ms "
        f"({r['straightforward_frames']} frames) -> speedup {r['speedup']:.0f}x, "
        f"identical clusters: {r['clusters_identical']}"
    )
    print(f"true clusters recovered: {r['true_clusters_recovered']}/{r['true_clusters']}")
    for k, t in r["targets"].items():
        print(f"target {k}: {t['target']} -> {'met' if t['met'] else 'NOT met'}")
    t = r.get("temporal")
    if t:
        print(
            f"temporal on  median {t['on_ms_median']:8.2f} ms   p90 {t['on_ms_p90']:8.2f} ms"
            f"   (first frame {t['on_first_frame_ms_median']:.2f} ms; "
            f"{t['detections_left_median']:.0f}/{t['detections_per_frame']} detections left "
            f"to cross-view association)"
        )
        print(
            f"temporal off median {t['off_ms_median']:8.2f} ms   p90 {t['off_ms_p90']:8.2f} ms"
            f"   -> off/on {t['off_over_on']:.1f}x over {t['frames']} moving frames; "
            f"true clusters in the last frame {t['true_clusters_last_frame']}/{t['players']}"
        )


def main(argv: list[str] | None = None) -> int:
    _pin_threads()
    args = _load_defaults(_parser().parse_args(argv))
    try:
        if args.live:
            from .live import check_live_arguments, run_live
            from .live_runs import run_repeated

            check_live_arguments(args)
            result = run_repeated(args, run_live)
        else:
            result = run(args)
    except ValueError as e:
        return fail("maem-bench", e)
    if args.live:
        import yaml

        print(
            json.dumps(_finite_or_null(result))
            if args.json
            else yaml.safe_dump(_finite_or_null(result), sort_keys=False)
        )
        return 0
    if args.json:
        print(json.dumps(_finite_or_null(result)))
    else:
        _print_human(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
