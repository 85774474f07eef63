"""maem-demo: replay the demo bag through the real node graph; print accuracy, timing and latency.

    maem-demo [--bag bags/demo] [--out out/demo] [--frames N | --duration S] [--rate R]
              [--params config/demo.yaml] [--keep-going] [--frontends | --no-graph]
    maem-demo --make-bag bags/demo        (regenerate the committed demo bag, seeded)
    maem-demo --bag BAG --backend mediapipe --out out/real   (real images, e.g. maem-make-bag --videos)

Graph mode (default) runs, each as its own process with one params file (OUT/params.yaml:
--params plus what the bag says, i.e. its rig): maem-record (/maem/poses, /maem/skeletons,
/diagnostics -> OUT/record), maem-association, maem-triangulation, and last maem-play, which
publishes the bag's recorded /<cam>/detections in real time (--rate 1.0, 30 fps): the live path
a user sees from the fusion machine, with a progress line. --frontends instead runs one
maem-frontend per camera (synthetic backend on /<cam>/image_raw/compressed: it regenerates the
full-resolution detections of each image stamp from the bag's scene description; association
max_wait 1 s as the six frontends share the CPU) and plays the bag's images without its
recorded detections, by default at rate 0.05. The association and triangulation run with
``keep_every_set: true``: the demo scores every frame, so nodes that fall behind on this machine
process every frame late instead of skipping the stale ones as a live graph does (said in the
output). At the end every process gets SIGINT and its exit
code is checked. --no-graph runs the core pipeline on the bag's recorded (vertex-subset)
detections in this process instead.

Printed: the maem-eval accuracy table against the bag's /maem/gt_poses (same metrics, see
maem-eval --help), per-stage timing from the last recorded /diagnostics of each node,
end-to-end latency and frames dropped. Written to OUT: report.json, snapshot_<cam>.png
(skeletons projected on a camera image), court.png (top-down view), logs/, record/.
report.json also has people_per_frame (people on /maem/poses per played frame),
reprojection_px_mean (see demo_metrics.REPROJECTION_DEFINITION) and bone_length_cv.

--backend mediapipe runs the frontends on the bag's images with multi-person BlazePose (the
optional mediapipe extra; default params config/mediapipe.yaml). Four CPU frontends can take
seconds per image each on a small machine, far slower than the 60 fps capture, so the replay
goes in lockstep:
maem-play publishes the next frame as soon as /maem/clusters has the last one (--lockstep,
at most 60 s per frame), at --rate (default 1) from there, and the images go reliable
(--reliable-images, frontends image_reliability: reliable): no image is lost to a full
best-effort queue and no frame set to the association's max_wait. A bag without ground truth
is reported without the accuracy table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.core.association.pipeline import associate
from maem_ros.core.errors import InputError
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.sync import capture_stamp_ns, match_capture_times
from maem_ros.core.triangulation.ransac import triangulate
from maem_ros.params import load_node_params
from maem_ros.tools.cli import fail
from maem_ros.tools.demo.demo_bag import (
    BAG_VERTICES,
    DEMO_SCENE,
    JPEG_QUALITY,
    DemoBag,
    check_scene,
    ensure_bag,
    load_bag,
    log,
    make_demo_bag,
    trim_bag,
)
from maem_ros.tools.demo.demo_graph import LOCKSTEP_BACKENDS, DemoError, run_graph, write_params
from maem_ros.tools.demo.demo_report import (
    LATENCY_DEFINITION,
    GraphRun,
    format_timing,
    latencies_ms,
    print_accuracy,
    print_run_summary,
    recorded_diagnostics,
    recorded_poses,
    score,
    stage_timing,
    write_pictures,
)
from maem_ros.tools.eval.evaluate import load_params, to_sportcenter13
from maem_ros.tools.eval.results import jsonable
from maem_ros.wire import msg_to_detections

#: default playback rate of the recorded detections: real time
DEFAULT_RATE = 1.0
#: default playback rate with --frontends (1.5 fps): each synthetic frontend regenerates
#: 18,439-vertex detections of ~12 people per image, a CPU-heavy step; all six get a frame at
#: the same moment and share the machine's cores with the rest of the graph, so on a small
#: machine faster replays drop frames
FRONTENDS_RATE = 0.05
#: --backend -> (default params file, default playback rate with frontends (None: FRONTENDS_RATE),
#: association max_wait s). mediapipe: four CPU frontends, each taking up to seconds per
#: image on a small machine, share its cores, so the replay goes in lockstep and the
#: association waits up to 3 s for a frame's last camera
BACKENDS = {"synthetic": ("demo.yaml", None, 1.0), "mediapipe": ("mediapipe.yaml", 1.0, 3.0)}


# ---------------------------------------------------------------------------------------------
# offline (--no-graph)
# ---------------------------------------------------------------------------------------------
@dataclass
class OfflinePose:
    ids: np.ndarray
    joints: np.ndarray
    scores: np.ndarray


def run_offline(
    demo: DemoBag, rig, params: str, stamps: Sequence[int]
) -> tuple[dict[int, OfflinePose], list[float]]:
    """Association + triangulation of the bag's recorded detections, per frame, in process."""
    assoc, tri = load_params(params)
    frames: dict[int, dict[str, Any]] = {s: {} for s in stamps}
    topics = [f"/{c}/detections" for c in demo.cameras]
    if not any(t in demo.info.topics for t in topics):
        raise ValueError(f"bag {str(demo.path)!r}: no /<camera>/detections to run --no-graph on")
    offsets = {c: rig[c].time_offset for c in rig.names}
    late = max([0.0] + [-o for o in offsets.values()])  # s, capture time beyond the stamps
    stop = stamps[-1] + 1 + int(round(late * 1e9)) if stamps else None
    received: dict[str, list] = {}
    for m in bagio.read_messages(demo.path, topics, stop_ns=stop, info=demo.info):
        dets = msg_to_detections(m.decode(), m.topic, rig.names)
        received.setdefault(dets.camera, []).append(dets)
    # each camera's message captured nearest each frame (stamp + the rig's time_offset)
    tolerance = int(np.median(np.diff(stamps)) // 2) if len(stamps) > 1 else 0
    for cam, msgs in received.items():
        msgs.sort(key=lambda d: d.stamp_ns)
        index = match_capture_times(stamps, [d.stamp_ns for d in msgs], offsets[cam], tolerance)
        for s, k in zip(stamps, index):
            if k >= 0:
                dets = msgs[k]
                dets.stamp_ns = capture_stamp_ns(dets.stamp_ns, offsets[cam])
                frames[s][cam] = dets
    out, ms = {}, []
    for s in stamps:
        t0 = time.perf_counter()
        result = associate(rig, frames[s], assoc)
        poses = triangulate(rig, frames[s], result.clusters, tri)
        ms.append(1e3 * (time.perf_counter() - t0))
        joints = np.asarray(poses.joints, np.float64)
        joints = to_sportcenter13(joints) if len(joints) else np.zeros((0, 13, 3))
        out[s] = OfflinePose(np.arange(len(joints)), joints, np.asarray(poses.scores, np.float64))
    return out, ms


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-demo",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog=f"{__doc__.split(chr(10) * 2, 2)[2]}\n{LATENCY_DEFINITION}.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--bag",
        type=Path,
        default=None,
        help="input bag, which must exist (default bags/demo, generated first when "
        "missing; --make-bag DIR builds one elsewhere)",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument(
        "--params",
        default=None,
        help="params file (default config/demo.yaml; config/mediapipe.yaml with --backend mediapipe)",
    )
    p.add_argument(
        "--backend",
        choices=sorted(BACKENDS),
        default="synthetic",
        help="frontend backend of the graph (default synthetic: the simulated "
        "detections of the bag's scene; mediapipe: BlazePose on the bag's images)",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument("--frames", type=int, default=None, help="play only the first N frames")
    g.add_argument(
        "--duration", type=float, default=None, metavar="S", help="play only the first S seconds of bag time"
    )
    p.add_argument(
        "--rate",
        type=float,
        default=None,
        help=f"playback rate (default {DEFAULT_RATE}, with --frontends "
        f"{FRONTENDS_RATE}; the bag is 30 fps; 1 with --backend mediapipe, in lockstep "
        "with the graph)",
    )
    p.add_argument(
        "--keep-going",
        action="store_true",
        help="finish the replay when a node crashes (reported at the end, exit 1)",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--no-graph",
        action="store_true",
        help="offline: core association + triangulation on the bag's recorded detections",
    )
    mode.add_argument(
        "--frontends",
        action="store_true",
        help="run the synthetic frontends on the bag's images instead of playing its recorded detections",
    )
    p.add_argument(
        "--startup-timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="give up when the graph is not wired after S seconds (default 60)",
    )
    p.add_argument(
        "--make-bag",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"only build the demo bag into DIR (seeded; JPEG quality {JPEG_QUALITY}, "
        f"{BAG_VERTICES} mesh vertices per recorded detection) and exit",
    )
    p.add_argument(
        "--bag-frames",
        type=int,
        default=DEMO_SCENE["frames"],
        metavar="N",
        help=f"frames of a generated demo bag (default {DEMO_SCENE['frames']})",
    )
    return p


def played_frames(demo: DemoBag, frames: int | None, duration: float | None) -> int:
    n = len(demo.stamps)
    if frames is not None:
        n = min(n, frames)
    if duration is not None:
        n = min(n, max(1, int(np.floor(duration * demo.fps + 1e-9)) + 1))
    return n


def prepare_out(out: Path) -> None:
    """Create ``out``; remove what a previous demo run wrote there (only those entries)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("record", "logs", "input", "params.yaml", "rig.yaml", "report.json", "court.png"):
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in out.glob("snapshot_*.png"):
        p.unlink()


def main(argv: Sequence[str] | None = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    if a.backend != "synthetic":
        if a.no_graph:
            p.error(f"--backend {a.backend} runs frontends on the bag's images; --no-graph has none")
        a.frontends = True  # only the frontends see images
    a.params = a.params or BACKENDS[a.backend][0]
    if a.rate is None and a.frontends:
        a.rate = BACKENDS[a.backend][1]
    if a.make_bag is not None:
        try:
            make_demo_bag(a.make_bag, frames=a.bag_frames)
        except (ValueError, RuntimeError) as e:
            return fail("maem-demo", e)
        return 0
    if a.rate is None:
        a.rate = FRONTENDS_RATE if a.frontends else DEFAULT_RATE
    if not a.rate > 0:
        return fail("maem-demo", f"--rate must be > 0, got {a.rate}")
    if (a.frames is not None and a.frames < 1) or (a.duration is not None and a.duration <= 0):
        return fail("maem-demo", "--frames / --duration must be positive")
    t_start = time.monotonic()
    try:
        return run_demo(a, t_start)
    except InputError as e:  # the bag (missing, damaged, not a demo bag), the params file
        return fail("maem-demo", e)
    except (ValueError, DemoError) as e:
        return fail("maem-demo", e, 1)


def offline_mode(
    a: argparse.Namespace, demo: DemoBag, rig, stamps: list[int]
) -> tuple[int, dict[int, Any], dict[str, Any]]:
    """--no-graph: (exit code, poses by stamp, report entries)."""
    poses, ms = run_offline(demo, rig, a.params, stamps)
    metrics = score(demo, stamps, {s: (p.joints, p.scores) for s, p in poses.items()})
    metrics["association_ms_median"] = float(np.median(ms))
    print_accuracy("offline (bag detections)", metrics)
    print(
        f"\ncore association + triangulation per frame: median {np.median(ms):.1f} ms, "
        f"p99 {np.percentile(ms, 99):.1f} ms (this process, bag's vertex subset)"
    )
    return 0, poses, {"metrics": metrics, "pipeline_ms_median": float(np.median(ms))}


def _replay_graph(
    a: argparse.Namespace, demo: DemoBag, rig_path: Path, stamps: list[int]
) -> tuple[GraphRun, Path]:
    """Check the bag has what the graph plays, write the graph's params file and replay the
    first len(stamps) frames through the node graph: (GraphRun, params file)."""
    if a.frontends and a.backend == "synthetic":
        check_scene(demo)
    elif not a.frontends and not any(f"/{c}/detections" in demo.info.topics for c in demo.cameras):
        raise ValueError(
            f"bag {str(demo.path)!r}: no recorded /<camera>/detections to play "
            f"(use --frontends to run the synthetic frontends on its images)"
        )
    n = len(stamps)
    play_bag = demo.path if n == len(demo.stamps) else trim_bag(demo, a.out / "input", n)
    params = write_params(
        a.params,
        a.out / "params.yaml",
        rig_path.resolve(),
        demo.scene_config,
        max_wait_s=BACKENDS[a.backend][2] if a.frontends else None,
        frontends=a.frontends,
        backend=a.backend if a.frontends else None,
    )
    lockstep = a.frontends and a.backend in LOCKSTEP_BACKENDS
    log(
        "every frame is processed however late (association and triangulation "
        "keep_every_set: true; a live graph skips the frames it falls behind on)"
        + ("; the replay goes in lockstep with /maem/clusters" if lockstep else "")
    )
    run = run_graph(
        play_bag,
        demo,
        stamps,
        params,
        a.out,
        a.rate,
        a.keep_going,
        startup_timeout_s=a.startup_timeout,
        frontends=a.frontends,
        lockstep=lockstep,
    )
    return run, params


def graph_mode(
    a: argparse.Namespace, demo: DemoBag, rig_path: Path, stamps: list[int]
) -> tuple[int, dict[int, Any], dict[str, Any]]:
    """The node graph replay: (exit code, recorded poses by stamp, report entries)."""
    run, params = _replay_graph(a, demo, rig_path, stamps)
    n = len(stamps)
    poses = recorded_poses(run.record)
    diags = recorded_diagnostics(run.record)
    metrics = score(demo, stamps, {s: (p.joints, p.scores) for s, p in poses.items()}) if demo.gt else {}
    assoc = next((kv for name, kv in diags.items() if name.strip("/") == "association"), {})
    metrics["association_ms_median"] = float(assoc.get("time_ms/associate/median", "nan"))
    if demo.gt:
        print_accuracy(
            "graph (maem-play -> frontends -> nodes)"
            if a.frontends
            else "graph (maem-play detections -> nodes)",
            metrics,
        )
    else:
        print("\nthe bag has no ground truth (/maem/gt_poses): no accuracy table")
    quality = real_capture_measures(run.record, Rig.load(rig_path), params, stamps, poses)
    rows = stage_timing(diags)
    print("\nper-stage timing (last /diagnostics of each node, over its last <= 200 frames):")
    print(format_timing(rows) if rows else "  no /diagnostics recorded")
    lat = latencies_ms(run.image_t, run.poses_t)
    dropped = [s for s in stamps if s not in poses]
    print_run_summary(a.rate, n, lat, dropped, diags, run)
    definition = (
        LATENCY_DEFINITION
        if a.frontends
        else LATENCY_DEFINITION.replace("/<cam>/image_raw/compressed", "/<cam>/detections").replace(
            "the frontends, synchronisation", "synchronisation"
        )
    )
    report = {
        "metrics": metrics,
        "latency_definition": definition,
        "timing": [
            dict(zip(("node", "stage", "median_ms", "p99_ms", "processed", "dropped"), r)) for r in rows
        ],
        "latency_ms_median": float(np.median(lat)) if len(lat) else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
        "frames_dropped": len(dropped),
        "exit_codes": run.exit_codes,
        **quality,
        "crashed": run.crashed,
        "record": str(run.record),
        "replay_wall_s": run.wall_s,
    }
    if run.crashed:
        print("\nNODE FAILURES:")
        for text in run.crashed.values():
            print(f"  {text}")
    return (1 if run.crashed else 0), poses, report


def open_demo_bag(a: argparse.Namespace) -> DemoBag:
    """The demo's input bag, read and checked; InputError (exit 2) when it is unusable."""
    bag = ensure_bag(a.bag, a.bag_frames)
    try:
        return load_bag(bag)
    except InputError:
        raise
    except ValueError as e:  # readable, but not a demo bag (no images, no rig ...)
        raise InputError(str(e), "bad_bag") from None


def real_capture_measures(
    record: Path, rig: Rig, params: Path, stamps: Sequence[int], poses: dict[int, Any]
) -> dict[str, Any]:
    """people_per_frame, reprojection and bone-length stability of the recorded run (printed)."""
    from maem_ros.core.skeleton import get_convention
    from maem_ros.params import load_node_params
    from maem_ros.tools.demo import demo_metrics as dm

    _, tri = load_params(str(params))
    conv = get_convention(
        load_node_params(params, "triangulation").get("output_convention", "sportcenter_13")
    )
    people = dm.people_per_frame(stamps, poses)
    reproj = dm.reprojection_summary(dm.reprojection_errors(record, rig, tri, stamps), tri.tau_kps)
    bones = dm.bone_length_cv(poses, conv)
    found = dm.joints_found(poses, conv)
    counts = np.bincount(people) if people else np.zeros(1, int)
    print(
        "\npeople per frame (/maem/poses): "
        + ", ".join(f"{k}: {c} frames" for k, c in enumerate(counts) if c)
    )
    if reproj["reprojection_pairs"]:
        print(
            f"reprojection error of the triangulated joints in their clusters' views: mean "
            f"{reproj['reprojection_px_mean']:.1f} px, median "
            f"{reproj['reprojection_px_median']:.1f} px, under tau_kps "
            f"{reproj['reprojection_px_mean_inliers']:.1f} px "
            f"({100 * reproj['reprojection_inlier_fraction']:.0f} % of "  # type: ignore[operator]  # a float here
            f"{reproj['reprojection_pairs']} joint-views); all members "
            f"{reproj['reprojection_px_mean_all_members']:.1f} px "
            f"({reproj['reprojection_members_rejected']} of {reproj['reprojection_members']} "
            f"members left out by tau_member)"
        )
    if found["joints_found"]:
        print(
            "joints found per published person: "
            + ", ".join(f"{j} {100 * v:.0f} %" for j, v in found["joints_found"].items())
        )
    if bones["bone_length_cv"]:
        print(
            f"bone length coefficient of variation over {bones['bone_length_tracks']} tracks: "
            + ", ".join(f"{b} {100 * v:.1f} %" for b, v in bones["bone_length_cv"].items())
        )
    return {
        "people_per_frame": people,
        **reproj,
        **bones,
        **found,
        "reprojection_definition": dm.REPROJECTION_DEFINITION,
    }


def run_demo(a: argparse.Namespace, t_start: float) -> int:
    load_node_params(a.params, "association")  # a bad params file: one line before any work
    demo = open_demo_bag(a)
    bag = demo.path
    prepare_out(a.out)
    stamps = demo.stamps[: played_frames(demo, a.frames, a.duration)]
    rig_path = a.out / "rig.yaml"
    rig_path.write_text(demo.rig_yaml)
    rig = Rig.load(rig_path)
    log(
        f"bag {str(bag)!r}: {len(demo.stamps)} frames x {len(demo.cameras)} cameras at "
        f"{demo.fps:.0f} fps; playing {len(stamps)} frames "
        + ("offline (--no-graph)" if a.no_graph else f"at rate {a.rate:g}")
    )
    mode = offline_mode(a, demo, rig, stamps) if a.no_graph else graph_mode(a, demo, rig_path, stamps)
    code, poses, entries = mode
    pictures = write_pictures(a.out, demo, rig, stamps, poses)
    report = {
        "bag": str(bag),
        "backend": a.backend,
        "frames_played": len(stamps),
        "cameras": demo.cameras,
        "mode": "offline" if a.no_graph else "graph",
        "rate": a.rate,
        **entries,
        "pictures": [str(p) for p in pictures],
        "wall_s": time.monotonic() - t_start,
    }
    (a.out / "report.json").write_text(json.dumps(jsonable(report), indent=2))
    print(
        f"\nwrote {', '.join(str(p) for p in pictures) or 'no pictures (no frame with poses)'}, "
        f"{a.out / 'report.json'}"
    )
    log(f"done in {report['wall_s']:.1f} s")
    return code


if __name__ == "__main__":
    sys.exit(main())
