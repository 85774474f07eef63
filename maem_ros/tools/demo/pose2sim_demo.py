"""maem-pose2sim-demo: a real multi-person capture, end to end on a CPU.

    maem-pose2sim-demo [--out out/pose2sim] [--frames N] [--cache DIR] [--rate R]
    maem-pose2sim-demo --bench N      (frontend time per image, in this process, no graph)
    maem-pose2sim-demo --offline      (every image through the same core code in this process)

Fetches Pose2Sim's Demo_MultiPerson (4 calibrated cameras, Qualisys Calib.qca.txt, 100 frames of
portrait 1088x1920 video at 60 fps, two people in a lab with bystanders) from the ``pose2sim``
wheel on PyPI (``pip download --no-deps pose2sim==0.10.49`` into the cache, ~51 MB, once; the
footage is extracted from the wheel, never committed), builds a bag with
``maem-make-bag --videos ... --rig Calib.qca.txt`` and runs ``maem-demo --backend mediapipe`` on
it (needs the mediapipe extra: make mediapipe). Everything lands in OUT: bag/, report.json,
snapshot_cam0N.png, court.png. --bench N runs the mediapipe frontend (config/mediapipe.yaml) on
the first N frames of every camera, one image at a time in this process, and prints the time per
image and per model pass (the machine's load matters: compare the two, measured in one run).
--offline runs frontend, association, triangulation and tracking (config/mediapipe.yaml) on every
frame in this process, so no image is lost to transport or a busy CPU, and writes
OUT/report_offline.json with the same measures as the graph run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from maem_ros.tools.cli import fail

POSE2SIM_VERSION = "0.10.49"
DEMO_PREFIX = "Pose2Sim/Demo_MultiPerson/"
BOARD_DEMO_PREFIX = "Pose2Sim/Demo_SinglePerson/calibration/"


def cache_dir() -> Path:
    """$MAEM_CACHE, else $XDG_CACHE_HOME/maem_ros, else ~/.cache/maem_ros."""
    if os.environ.get("MAEM_CACHE"):
        return Path(os.environ["MAEM_CACHE"]).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "maem_ros"


def fetch_demo(cache: Path | None = None, timeout_s: float = 600.0) -> Path:
    """The Demo_MultiPerson folder (calibration/Calib.qca.txt, videos/cam0N.mp4), downloaded and
    extracted into ``cache`` on first use; RuntimeError when the wheel cannot be had."""
    cache = (cache or cache_dir()) / f"pose2sim-{POSE2SIM_VERSION}"
    demo = cache / DEMO_PREFIX
    if (demo / "calibration" / "Calib.qca.txt").is_file() and len(list((demo / "videos").glob("*.mp4"))) == 4:
        return demo
    wheel = _wheel(cache, timeout_s)
    _extract(
        wheel,
        cache,
        lambda m: m.startswith(DEMO_PREFIX) and (m.endswith(".mp4") or m.endswith(".qca.txt")),
        f"{DEMO_PREFIX} videos/calibration",
    )
    return demo


def fetch_board_demo(cache: Path | None = None, timeout_s: float = 600.0) -> Path:
    """Demo_SinglePerson's calibration folder from the same wheel: Calib.qca.txt and
    intrinsics/int_camXX_img/*.jpg (checkerboard photos, 4x7 inner corners, 60 mm squares,
    taken one camera at a time); RuntimeError when the wheel cannot be had."""
    cache = (cache or cache_dir()) / f"pose2sim-{POSE2SIM_VERSION}"
    calib = cache / BOARD_DEMO_PREFIX
    if (calib / "Calib.qca.txt").is_file() and len(list(calib.glob("intrinsics/*/*.jpg"))) >= 4:
        return calib
    wheel = _wheel(cache, timeout_s)
    _extract(
        wheel,
        cache,
        lambda m: m.startswith(BOARD_DEMO_PREFIX) and (m.endswith(".jpg") or m.endswith(".qca.txt")),
        f"{BOARD_DEMO_PREFIX} images",
    )
    return calib


def _wheel(cache: Path, timeout_s: float) -> Path:
    """The pose2sim wheel in ``cache``, downloaded by pip on first use."""
    cache.mkdir(parents=True, exist_ok=True)
    wheels = sorted(cache.glob(f"pose2sim-{POSE2SIM_VERSION}-*.whl"))
    if not wheels:
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--quiet",
            "--dest",
            str(cache),
            f"pose2sim=={POSE2SIM_VERSION}",
        ]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(
                f"pip download pose2sim=={POSE2SIM_VERSION}: no answer in {timeout_s:.0f} s"
            ) from None
        wheels = sorted(cache.glob(f"pose2sim-{POSE2SIM_VERSION}-*.whl"))
        if done.returncode != 0 or not wheels:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"pip download pose2sim=={POSE2SIM_VERSION} failed: {tail[0]}")
    return wheels[0]


def _extract(wheel: Path, cache: Path, wanted, what: str) -> None:
    """Extract the wheel's members ``wanted(name)`` into ``cache``."""
    try:
        with zipfile.ZipFile(wheel) as z:
            members = [m for m in z.namelist() if wanted(m)]
            if not members:
                raise RuntimeError(f"wheel {wheel.name}: no {what}")
            z.extractall(cache, members)
    except zipfile.BadZipFile:
        wheel.unlink()
        raise RuntimeError(f"wheel {wheel.name}: not a zip file (removed; run again)") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-pose2sim-demo",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog=__doc__.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("out/pose2sim"), help="output folder")
    p.add_argument("--frames", type=int, default=None, help="play only the first N frames")
    p.add_argument("--cache", type=Path, default=None, help=f"download cache (default {cache_dir()})")
    p.add_argument("--rate", type=float, default=None, help="playback rate (maem-demo default)")
    p.add_argument(
        "--bench",
        type=int,
        default=None,
        metavar="N",
        help="only time the mediapipe frontend on N frames per camera",
    )
    p.add_argument(
        "--rig",
        type=Path,
        default=None,
        help="run with this rig (e.g. one from maem-calibrate people) instead of the "
        "demo's Qualisys Calib.qca.txt; same camera names and intrinsics",
    )
    p.add_argument(
        "--offline",
        action="store_true",
        help="no graph: every frame through frontend, association, triangulation "
        "and tracking in this process (OUT/report_offline.json)",
    )
    return p


def run_offline(
    root: Path, frames: int | None, rig_path: Path | None = None, detections: dict | None = None
) -> dict:
    """Every frame (or the first ``frames``) of the four videos through the core pipeline.

    ``rig_path``: the rig to associate and triangulate with (default the demo's Calib.qca.txt;
    a self-calibrated rig has the same intrinsics, so the frontend's output is the same);
    ``detections``: {camera: [FrameDetections | None per frame]} already made by the frontend
    (then the videos are not read again)."""
    import cv2
    import numpy as np

    from maem_ros.core.association import AssociationParams
    from maem_ros.core.geometry.camera import Rig
    from maem_ros.core.skeleton import get_convention
    from maem_ros.core.triangulation.ransac import TriangulationParams
    from maem_ros.frontend.base import make_estimator
    from maem_ros.frontend.rectify import Rectifier
    from maem_ros.params import load_node_params
    from maem_ros.tools.demo import demo_metrics as dm
    from maem_ros.wire import UNTRACKED_ID, PoseFrame

    rig = Rig.load(rig_path or root / "calibration" / "Calib.qca.txt")
    node = {n: load_node_params("mediapipe.yaml", n) for n in ("frontend", "association", "triangulation")}
    assoc = AssociationParams.from_mapping(node["association"])
    tri = TriangulationParams.from_mapping(node["triangulation"])
    out_conv = get_convention(node["triangulation"].get("output_convention", "sportcenter_13"))
    tracker, bone_filter = _offline_tracking(node["triangulation"], out_conv.names)
    # MediapipeEstimator each (make_estimator's type is the base class): its .stats counters
    ests: dict[str, Any] = (
        {}
        if detections is not None
        else {c.name: make_estimator("mediapipe", node["frontend"], rig) for c in rig}
    )
    rects = {c.name: Rectifier(c) for c in rig}
    caps = (
        {}
        if detections is not None
        else {c.name: cv2.VideoCapture(str(root / "videos" / f"{c.name}.mp4")) for c in rig}
    )
    fps = caps[rig.names[0]].get(cv2.CAP_PROP_FPS) if caps else 60.0
    fps = fps or 60.0
    P_rig = np.stack([c.P for c in rig])
    poses_by_stamp, errs, stamps, k = {}, dm.MemberErrors(), [], 0
    while frames is None or k < frames:
        stamp = int(round(k * 1e9 / fps))
        if detections is not None:
            if k >= min(len(v) for v in detections.values()):
                break
            dets = {c.name: _given(detections[c.name][k], c, stamp) for c in rig}
        else:
            images = {name: cap.read() for name, cap in caps.items()}
            if not all(ok for ok, _ in images.values()):
                break
            dets = {
                c.name: ests[c.name].estimate(c, stamp, rects[c.name].rectify(images[c.name][1])) for c in rig
            }
        joints = _frame_joints(rig, P_rig, dets, assoc, tri, out_conv, errs)
        ids = np.asarray(tracker.update(stamp, joints), np.int64)
        if bone_filter is not None:
            bone_filter.apply(ids, joints)  # the triangulation node's bone_tolerance
        ids = np.where(ids >= 0, ids, UNTRACKED_ID)
        poses_by_stamp[stamp] = PoseFrame(stamp, "world", ids, joints, np.zeros(len(ids)), np.ones(len(ids)))
        stamps.append(stamp)
        k += 1
    for cap in caps.values():
        cap.release()
    people = dm.people_per_frame(stamps, poses_by_stamp)
    return {
        "mode": "offline",
        "frames": len(stamps),
        "people_per_frame": people,
        **dm.reprojection_summary(errs, tri.tau_kps),
        **dm.bone_length_cv(poses_by_stamp, out_conv),
        **dm.joints_found(poses_by_stamp, out_conv),
        "rig": str(rig_path or root / "calibration" / "Calib.qca.txt"),
        "frontend_stats": {n: e.stats for n, e in ests.items()},
        "reprojection_definition": dm.REPROJECTION_DEFINITION,
    }


def _offline_tracking(tri_params: dict, joint_names: Sequence[str]) -> tuple[Any, Any]:
    """The triangulation node's post-hoc 3D tracker and bone-length filter (None when
    ``bone_tolerance`` is 0) from its parameters, as the node makes them."""
    from maem_ros.core.tracking.bone_filter import BoneLengthFilter
    from maem_ros.core.tracking.tracks import Tracker

    tracker = Tracker(
        tri_params.get("track_gate", 0.5),
        tri_params.get("track_min_hits", 3),
        tri_params.get("track_timeout", 1.0),
    )
    tolerance = float(tri_params.get("bone_tolerance", 0.0))
    return tracker, (BoneLengthFilter(joint_names, tolerance) if tolerance > 0 else None)


def _frame_joints(rig, P_rig, dets: dict, assoc, tri, out_conv, errs) -> Any:
    """(P,J_out,3) world m joints of one frame's associated and triangulated people (in
    ``out_conv``); each member's reprojection errors added to ``errs`` (demo_metrics)."""
    import numpy as np

    from maem_ros.core.association import associate
    from maem_ros.core.skeleton import convert as convert_joints
    from maem_ros.core.triangulation.ransac import pad_members
    from maem_ros.tools.demo import demo_metrics as dm

    clusters = associate(rig, dets, assoc).clusters
    rows = [(i, int(c), int(d)) for i, cl in enumerate(clusters) for c, d in cl.members]
    if not rows:
        return np.zeros((0, out_conv.num_joints, 3))
    which, cam, det = (np.array(x) for x in zip(*rows))
    kp = np.stack([dets[rig.names[c]].kpts2d[d] for c, d in zip(cam, det)])
    sc = np.array([dets[rig.names[c]].scores[d] for c, d in zip(cam, det)])
    poses, e = dm.member_reprojection_errors(P_rig, *pad_members(which, cam, kp, sc), tri)
    errs.add(e)
    return convert_joints(np.asarray(poses.joints), out_conv)


def _given(d, camera, stamp: int):
    """A frame's given detections restamped to ``stamp`` (None: an empty frame)."""
    import dataclasses

    from maem_ros.core.detections import FrameDetections
    from maem_ros.core.skeleton import BLAZEPOSE_33

    if d is None:
        return FrameDetections.empty(camera.name, stamp, BLAZEPOSE_33.num_joints, 0)
    return dataclasses.replace(d, stamp_ns=stamp)


def bench_frontend(root: Path, frames: int) -> dict:
    """Time the mediapipe frontend on the first ``frames`` frames of each camera (ms)."""
    import time

    import cv2
    import numpy as np

    from maem_ros.core.geometry.camera import Rig
    from maem_ros.frontend.base import make_estimator
    from maem_ros.frontend.rectify import Rectifier
    from maem_ros.params import load_node_params

    rig = Rig.load(root / "calibration" / "Calib.qca.txt")
    options = load_node_params("mediapipe.yaml", "frontend")
    per_image, rectify_ms, people, calls, images = [], [], [], 0, 0
    for cam in rig:
        est: Any = make_estimator("mediapipe", options, rig)  # a MediapipeEstimator (.stats)
        rect = Rectifier(cam)
        cap = cv2.VideoCapture(str(root / "videos" / f"{cam.name}.mp4"))
        for k in range(frames):
            ok, img = cap.read()
            if not ok:
                break
            t0 = time.perf_counter()
            r = rect.rectify(img)
            t1 = time.perf_counter()
            dets = est.estimate(cam, k, r)
            t2 = time.perf_counter()
            if k:  # frame 0 includes the model's start-up
                rectify_ms.append(1e3 * (t1 - t0))
                per_image.append(1e3 * (t2 - t1))
            people.append(dets.n)
        cap.release()
        calls += est.stats["passes"]
        images += est.stats["frames"]
    per_pass = calls / max(images, 1)
    out = {
        "images": len(per_image),
        "estimate_ms_median": float(np.median(per_image)),
        "estimate_ms_p90": float(np.percentile(per_image, 90)),
        "rectify_ms_median": float(np.median(rectify_ms)),
        "people_per_image_mean": float(np.mean(people)),
        "model_passes_per_image": per_pass,
        "ms_per_model_pass": float(np.median(per_image)) / per_pass,
    }
    return out


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    from maem_ros.tools.bags import make_bag
    from maem_ros.tools.demo import demo

    try:
        root = fetch_demo(a.cache)
    except RuntimeError as e:
        return fail("maem-pose2sim-demo", e)
    if a.bench is not None:
        if a.bench < 2:
            return fail("maem-pose2sim-demo", "--bench needs N >= 2 frames")
        try:
            result = bench_frontend(root, a.bench)
        except ImportError as e:
            return fail("maem-pose2sim-demo", e)
        print(
            "mediapipe frontend, in-process, one image at a time (frame 0 excluded): "
            + ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in result.items())
        )
        print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
        return 0
    if a.offline:
        import json

        try:
            report = run_offline(root, a.frames, a.rig)
        except ImportError as e:
            return fail("maem-pose2sim-demo", e)
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "report_offline.json").write_text(json.dumps(report, indent=2))
        people = report["people_per_frame"]
        both = sum(p >= 2 for p in people)
        print(
            f"offline, {report['frames']} frames: >= 2 people in {both} frames "
            f"({sum(p == 2 for p in people)} exactly 2); reprojection mean "
            f"{report['reprojection_px_mean']:.1f} px, median "
            f"{report['reprojection_px_median']:.1f} px, under tau_kps "
            f"{report['reprojection_px_mean_inliers']:.1f} px; bone length CV mean "
            f"{100 * (report['bone_length_cv_mean'] or 0):.1f} %, max "
            f"{100 * (report['bone_length_cv_max'] or 0):.1f} %; joints found "
            f"{100 * (report['joints_found_mean'] or 0):.0f} %; wrote "
            f"{a.out / 'report_offline.json'}"
        )
        return 0
    bag = a.out / "bag"
    if not (bag / "metadata.yaml").is_file():
        a.out.mkdir(parents=True, exist_ok=True)
        code = make_bag.main(
            [
                str(bag),
                "--videos",
                str(root / "videos"),
                "--rig",
                str(a.rig or root / "calibration" / "Calib.qca.txt"),
                "--quiet",
            ]
        )
        if code != 0:
            return code
    args = ["--bag", str(bag), "--backend", "mediapipe", "--out", str(a.out)]
    if a.frames is not None:
        args += ["--frames", str(a.frames)]
    if a.rate is not None:
        args += ["--rate", str(a.rate)]
    return demo.main(args)


if __name__ == "__main__":
    sys.exit(main())
