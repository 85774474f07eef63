"""``maem-calibrate people``: calibrate a rig from the players (extrinsics, floor, scale, time).

SOURCE is a MAEM scene folder (``dets/<cam>/*.npz``), a bag with ``/<cam>/detections``, or a
folder of per-camera image folders / videos (``<cam>/*.jpg`` or ``<cam>.mp4``) run through a
frontend backend. ``--intrinsics`` gives K, distortion and image size (any rig format the
project reads; extrinsics there are ignored). Writes the rig (YAML, or Pose2Sim TOML with
``--format toml``), prints a per-camera summary, and with ``--report DIR`` draws pictures.
How-to: doc/calibration.md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..core.detections import FrameDetections
from ..core.geometry.camera import Rig
from ..core.interchange import DEFAULT_FPS, index_frame_files, outputs_to_detections, read_maem_npz

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


class BadInput(ValueError):
    """Input the user must fix: printed on one line, exit 2."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, help="scene folder, bag, or folder of per-camera images/videos")
    p.add_argument("--intrinsics", type=Path, required=True,
                   help="rig file or folder with every camera's K, distortion, image size")
    p.add_argument("--out", type=Path, required=True, help="rig file to write")
    p.add_argument("--format", choices=("yaml", "toml"), default=None,
                   help="yaml (the nodes' rig) or toml (Pose2Sim Calib.toml); default by --out suffix")
    p.add_argument("--report", type=Path, default=None, help="folder for the report's pictures")
    p.add_argument("--court-points", type=Path, default=None,
                   help="YAML of court landmarks and their pixels (fixes origin, axes, scale)")
    p.add_argument("--person-height", type=float, default=None,
                   help="the people's median stature in m (sets the scale)")
    p.add_argument("--refine-intrinsics", action="store_true", help="also refine focal length and k1")
    p.add_argument("--no-time", action="store_true", help="do not estimate time offsets")
    p.add_argument("--max-offset", type=float, default=0.15, help="largest time offset searched, s")
    p.add_argument("--backend", default="mediapipe",
                   help="frontend backend for image/video sources (mediapipe, synthetic, sam3d_body)")
    p.add_argument("--frames", type=int, default=None, help="use at most this many frames")
    p.add_argument("--fps", type=float, default=None, help="frame rate of an image/video source")


def run(args: argparse.Namespace) -> int:
    from ..core.calibrate.people import calibrate_people
    from ..core.calibrate.people_data import people_data
    from .calibrate_report import print_summary, write_report
    try:
        opts = _options(args)
        intr = _intrinsics(args.intrinsics)
        frames, fps, images = load_source(args.source, intr, args)
        data = people_data(intr, frames, fps)
    except BadInput as e:
        print(f"maem-calibrate people: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"maem-calibrate people: {e}", file=sys.stderr)
        return 2
    try:
        result = calibrate_people(data, opts)
    except ValueError as e:
        print(f"maem-calibrate people: {e}", file=sys.stderr)
        return 1
    fmt = args.format or ("toml" if args.out.suffix.lower() == ".toml" else "yaml")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "toml":
        from ..core.geometry.rig_formats import write_pose2sim_toml
        write_pose2sim_toml(args.out, result.rig.cameras)
    else:
        result.rig.to_yaml(args.out)
    print_summary(result, data, sys.stdout)
    print(f"rig written: {args.out}")
    if args.report is not None:
        for path in write_report(result, data, args.report, images):
            print(f"report: {path}")
    return 0


def _options(args):
    from ..core.calibrate.court import read_court_points
    from ..core.calibrate.people import PeopleOptions
    if args.person_height is not None and not (0.5 < args.person_height < 2.6):
        raise BadInput(f"--person-height: {args.person_height} m is not a person's stature")
    if args.frames is not None and args.frames < 2:
        raise BadInput(f"--frames: {args.frames}: need at least 2")
    court = read_court_points(args.court_points) if args.court_points is not None else None
    return PeopleOptions(refine_intrinsics=args.refine_intrinsics, estimate_time=not args.no_time,
                         max_offset_s=args.max_offset, person_height=args.person_height, court=court)


def _intrinsics(path: Path) -> Rig:
    if not path.exists():
        raise BadInput(f"--intrinsics {str(path)!r}: no such file or folder")
    return Rig.load_intrinsics(path)


def load_source(src: Path, intr: Rig, args) -> tuple[dict, float, dict]:
    """({camera: [FrameDetections | None per frame]}, fps, {(camera, frame): image path})."""
    if not src.exists():
        raise BadInput(f"source {str(src)!r}: no such file or folder")
    if src.is_dir() and (src / "dets").is_dir():
        return _scene_folder(src, intr, args.frames)
    if src.suffix == ".mcap" or (src.is_dir() and (src / "metadata.yaml").is_file()):
        return _bag(src, intr, args.frames)
    if src.is_dir():
        return _media(src, intr, args)
    raise BadInput(f"source {str(src)!r}: not a scene folder (dets/), a bag or a folder of "
                   f"per-camera images/videos")


def _check_cameras(found: list[str], intr: Rig, what: str) -> None:
    missing = [c for c in found if c not in intr]
    if missing:
        raise BadInput(f"--intrinsics: no intrinsics for camera(s) {', '.join(missing)} of {what}")


def _scene_folder(src: Path, intr: Rig, max_frames: int | None):
    import json
    views = sorted(p.name for p in (src / "dets").iterdir() if p.is_dir())
    _check_cameras(views, intr, f"scene {str(src)!r}")
    info = json.loads((src / "scene.json").read_text()) if (src / "scene.json").is_file() else {}
    fps = float(info.get("fps", DEFAULT_FPS))
    files = {v: index_frame_files(src / "dets" / v) for v in views}
    n = max((max(f) + 1 for f in files.values() if f), default=0)
    n = min(n, max_frames) if max_frames else n
    frames = {}
    for v in views:
        cam = intr[v]
        frames[v] = [outputs_to_detections(read_maem_npz(files[v][k]), cam, k,
                                           where=f"npz {str(files[v][k])!r} outputs")
                     if k in files[v] else None for k in range(n)]
    images = {(v, k): p for v in views for k in range(n)
              if (p := src / "images" / v / f"{k:06d}.jpg").is_file()}
    return frames, fps, images


def _bag(src: Path, intr: Rig, max_frames: int | None):
    from .. import bagio
    from ..ros.wire import msg_to_detections  # the wire decoder (needs rclpy's message types)
    info = bagio.bag_info(src)
    topics = sorted(t for t in info.topics if t.endswith("/detections"))
    if not topics:
        raise BadInput(f"bag {str(src)!r}: no /<camera>/detections topic (run the frontend first, "
                       f"or give the images' folder with --backend)")
    cams = [t.strip("/").split("/")[0] for t in topics]
    _check_cameras(cams, intr, f"bag {str(src)!r}")
    per_cam: dict[str, list[FrameDetections]] = {c: [] for c in cams}
    for m in bagio.read_messages(src, topics):
        det = msg_to_detections(m.decode(), m.topic)
        per_cam[m.topic.strip("/").split("/")[0]].append(det)
    stamps = np.concatenate([[d.stamp_ns for d in v] for v in per_cam.values() if v])
    if stamps.size < 2:
        raise BadInput(f"bag {str(src)!r}: fewer than two detection messages")
    period = float(np.median(np.diff(np.unique(stamps)))) or 1e9 / DEFAULT_FPS
    t0 = stamps.min()
    n = int(round((stamps.max() - t0) / period)) + 1
    n = min(n, max_frames) if max_frames else n
    frames = {}
    for c, dets in per_cam.items():
        seq: list[FrameDetections | None] = [None] * n
        for d in dets:
            k = int(round((d.stamp_ns - t0) / period))
            if 0 <= k < n:
                seq[k] = d
        frames[c] = seq
    return frames, 1e9 / period, {}


def _media(src: Path, intr: Rig, args):
    """Per-camera image folders or videos through a frontend backend."""
    import cv2

    from ..frontend.base import make_estimator
    entries: dict[str, list[Path] | Path] = {}
    for p in sorted(src.iterdir()):
        if p.is_dir() and any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()):
            entries[p.name] = sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            entries[p.stem] = p
    if not entries:
        raise BadInput(f"source {str(src)!r}: no per-camera image folders or videos")
    _check_cameras(list(entries), intr, f"source {str(src)!r}")
    fps = float(args.fps or DEFAULT_FPS)
    limit = args.frames or 10 ** 9
    est = make_estimator(args.backend, {}, Rig([intr[c] for c in entries]))
    frames, images = {}, {}
    for cam, what in entries.items():
        seq = []
        for k, img in enumerate(_images(what, limit, cv2)):
            seq.append(est.estimate(intr[cam], int(round(k * 1e9 / fps)), img))
            if isinstance(what, list):  # image files can be overlaid in the report
                images[(cam, k)] = what[k]
        frames[cam] = seq
    return frames, fps, images


def _images(what, limit: int, cv2):
    if isinstance(what, list):
        for path in what[:limit]:
            img = cv2.imread(str(path))
            if img is None:
                raise BadInput(f"image {str(path)!r}: unreadable")
            yield img
        return
    cap = cv2.VideoCapture(str(what))
    if not cap.isOpened():
        raise BadInput(f"video {str(what)!r}: cannot open")
    try:
        for _ in range(limit):
            ok, img = cap.read()
            if not ok:
                break
            yield img
    finally:
        cap.release()
