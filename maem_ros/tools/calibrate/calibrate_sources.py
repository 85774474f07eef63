"""The detections ``maem-calibrate people`` calibrates from, read from any SOURCE kind.

* a MAEM scene folder (``dets/<cam>/*.npz``, ``scene.json`` for the frame rate);
* a bag (rosbag2 / MCAP) with ``/<cam>/detections``, or with ``/<cam>/image_raw[/compressed]``
  run through a frontend backend (when it has no detections, or ``--backend`` is given);
* a folder of per-camera image folders (``<cam>/*.jpg``) or videos (``<cam>.mp4``) run through
  a frontend backend.

Images are rectified with each camera's intrinsics before the backend sees them (a frontend
works in rectified px, as the frontend node does). Backend options come from a node params
file's ``frontend`` section (``--frontend-params``; default ``config/<backend>.yaml`` when the
project ships one, e.g. config/mediapipe.yaml). The synthetic backend takes its scene from the
bag's recorded scene description when the params give none. ``--save-detections BAG`` writes
what a backend found as a bag of ``/<cam>/detections`` (the frontend's costly part, reusable as
a SOURCE). Every problem the user must fix raises :class:`BadInput` (one line, exit 2).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.interchange import DEFAULT_FPS, index_frame_files, outputs_to_detections, read_maem_npz

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")

#: {camera: [FrameDetections | None per frame]}, frame rate (Hz), {(camera, frame): image path}
Loaded = tuple[dict[str, list[FrameDetections | None]], float, dict[tuple[str, int], Path]]


class BadInput(ValueError):
    """Input the user must fix: printed on one line, exit 2."""


def load_source(src: Path, intr: Rig, args: argparse.Namespace) -> Loaded:
    """The detections of SOURCE ``src`` for the cameras of ``intr`` (rectified px)."""
    if not src.exists():
        raise BadInput(f"source {str(src)!r}: no such file or folder")
    if src.is_dir() and (src / "dets").is_dir():
        loaded = _scene_folder(src, intr, args.frames)
    elif src.suffix == ".mcap" or (src.is_dir() and (src / "metadata.yaml").is_file()):
        loaded = _bag(src, intr, args)
    elif src.is_dir():
        loaded = _media(src, intr, args)
    else:
        raise BadInput(
            f"source {str(src)!r}: not a scene folder (dets/), a bag or a folder of per-camera images/videos"
        )
    if getattr(args, "save_detections", None) is not None:
        save_detections(args.save_detections, loaded[0], loaded[1])
    return loaded


def _check_cameras(found: list[str], intr: Rig, what: str) -> None:
    missing = [c for c in found if c not in intr]
    if missing:
        raise BadInput(f"--intrinsics: no intrinsics for camera(s) {', '.join(missing)} of {what}")


def _scene_folder(src: Path, intr: Rig, max_frames: int | None) -> Loaded:
    views = sorted(p.name for p in (src / "dets").iterdir() if p.is_dir())
    _check_cameras(views, intr, f"scene {str(src)!r}")
    info = json.loads((src / "scene.json").read_text()) if (src / "scene.json").is_file() else {}
    fps = float(info.get("fps", DEFAULT_FPS))
    files = {v: index_frame_files(src / "dets" / v) for v in views}
    n = max((max(f) + 1 for f in files.values() if f), default=0)
    n = min(n, max_frames) if max_frames else n
    frames: dict[str, list[FrameDetections | None]] = {}
    for v in views:
        cam = intr[v]
        frames[v] = [
            outputs_to_detections(
                read_maem_npz(files[v][k]), cam, k, where=f"npz {str(files[v][k])!r} outputs"
            )
            if k in files[v]
            else None
            for k in range(n)
        ]
    images = {
        (v, k): p for v in views for k in range(n) if (p := src / "images" / v / f"{k:06d}.jpg").is_file()
    }
    return frames, fps, images


def _bag(src: Path, intr: Rig, args: argparse.Namespace) -> Loaded:
    from maem_ros import bagio

    try:
        info = bagio.bag_info(src)
    except (ValueError, OSError) as e:
        raise BadInput(f"bag {str(src)!r}: unreadable ({' '.join(str(e).split())})") from None
    dets = sorted(t for t in info.topics if t.endswith("/detections"))
    imgs = sorted(t for t, ty in info.topics.items() if bagio.is_image_type(ty) and "/image_raw" in t)
    if dets and args.backend is None:
        stamped = _bag_detections(src, dets, intr)
    elif imgs:
        stamped = _bag_images(src, imgs, intr, args)
    else:
        raise BadInput(
            f"bag {str(src)!r}: no /<camera>/detections topic and no "
            f"/<camera>/image_raw images (record the frontends or the cameras)"
        )
    return _frames_from_stamps(stamped, args.frames, str(src))


def _camera_of(topic: str) -> str:
    return topic.strip("/").split("/")[0]


def _bag_detections(src: Path, topics: list[str], intr: Rig) -> dict[str, list[FrameDetections]]:
    from maem_ros import bagio
    from maem_ros.wire import msg_to_detections  # the wire decoder (no rclpy)

    cams = [_camera_of(t) for t in topics]
    _check_cameras(cams, intr, f"bag {str(src)!r}")
    per_cam: dict[str, list[FrameDetections]] = {c: [] for c in cams}
    for m in bagio.read_messages(src, topics):
        try:
            per_cam[_camera_of(m.topic)].append(msg_to_detections(m.decode(), m.topic))
        except ValueError as e:
            raise BadInput(f"bag {str(src)!r}: {' '.join(str(e).split())}") from None
    return per_cam


def _bag_images(
    src: Path, topics: list[str], intr: Rig, args: argparse.Namespace
) -> dict[str, list[FrameDetections]]:
    """Every image message of the bag through the backend (rectified first)."""
    from maem_ros import bagio
    from maem_ros.frontend.rectify import Rectifier
    from maem_ros.wire import compressed_to_bgr, image_to_bgr

    by_cam: dict[str, str] = {}
    for t in topics:  # one image topic per camera; the compressed one if both were recorded
        if t.endswith("/compressed") or _camera_of(t) not in by_cam:
            by_cam[_camera_of(t)] = t
    cams = sorted(by_cam)
    _check_cameras(cams, intr, f"bag {str(src)!r}")
    backend = args.backend or "mediapipe"
    options = frontend_options(backend, args.frontend_params)
    if backend == "synthetic" and "scene_dict" not in options:
        scene = bagio.read_scene_config(src)
        if scene is None:
            raise BadInput(
                f"bag {str(src)!r}: no scene description (/maem/scene): the synthetic "
                f"backend cannot regenerate its detections"
            )
        options["scene_dict"] = scene
    est = _estimator(backend, options, Rig([intr[c] for c in cams]))
    rect = {c: Rectifier(intr[c]) for c in cams}
    per_cam: dict[str, list[FrameDetections]] = {c: [] for c in cams}
    limit = args.frames or 10**9
    for m in bagio.read_messages(src, list(by_cam.values())):
        cam = _camera_of(m.topic)
        if m.topic != by_cam[cam] or len(per_cam[cam]) >= limit:
            continue
        msg = m.decode()
        decode = compressed_to_bgr if m.topic.endswith("/compressed") else image_to_bgr
        stamp = bagio.stamp_to_ns(msg.header.stamp)
        image = rect[cam].rectify(decode(msg, m.topic)) if est.needs_image else None
        per_cam[cam].append(_estimate(est, intr[cam], stamp, image, m.topic))
    return per_cam


def _frames_from_stamps(
    per_cam: dict[str, list[FrameDetections]], max_frames: int | None, where: str
) -> Loaded:
    """Per-camera stamped detections on one frame index (the median stamp step)."""
    stamps = np.concatenate([[d.stamp_ns for d in v] for v in per_cam.values() if v] or [[]])
    if np.unique(stamps).size < 2:
        raise BadInput(f"bag {where!r}: fewer than two frames of detections")
    period = float(np.median(np.diff(np.unique(stamps)))) or 1e9 / DEFAULT_FPS
    t0 = stamps.min()
    n = int(round((stamps.max() - t0) / period)) + 1
    n = min(n, max_frames) if max_frames else n
    frames: dict[str, list[FrameDetections | None]] = {}
    for c, dets in per_cam.items():
        seq: list[FrameDetections | None] = [None] * n
        for d in dets:
            k = int(round((d.stamp_ns - t0) / period))
            if 0 <= k < n:
                seq[k] = d
        frames[c] = seq
    return frames, 1e9 / period, {}


def frontend_options(backend: str, params: Path | None) -> dict[str, Any]:
    """The ``frontend`` section of ``params`` (a node params file), else of the project's
    config/<backend>.yaml when it ships one for this backend, else no options."""
    from maem_ros.params import InputError, load_node_params, resolve_config_path

    if params is None:
        try:
            params = resolve_config_path(f"{backend}.yaml")
        except InputError:
            return {}
    try:
        options = load_node_params(params, "frontend")
    except (InputError, ValueError) as e:
        raise BadInput(f"--frontend-params: {' '.join(str(e).split())}") from None
    if options.get("backend", backend) != backend:  # the file is for another backend: its
        return {}  # options would not apply
    return {k: v for k, v in options.items() if k != "backend"}


def _estimator(backend: str, options: dict[str, Any], rig: Rig):
    from maem_ros.frontend.base import make_estimator

    try:
        return make_estimator(backend, options, rig)
    except ImportError as e:
        raise BadInput(f"--backend {backend}: {' '.join(str(e).split())}") from None
    except ValueError as e:
        raise BadInput(f"--backend {backend}: {' '.join(str(e).split())}") from None


def _estimate(est, camera, stamp: int, image, where: str) -> FrameDetections:
    try:
        return est.estimate(camera, stamp, image)
    except ValueError as e:
        raise BadInput(f"{where}: {' '.join(str(e).split())}") from None


def _media(src: Path, intr: Rig, args: argparse.Namespace) -> Loaded:
    """Per-camera image folders or videos through a frontend backend; frame k is stamped
    k / fps s (fps: --fps, else the first video's, else 30)."""
    from maem_ros.frontend.rectify import Rectifier

    entries: dict[str, list[Path] | Path] = {}
    for p in sorted(src.iterdir()):
        if p.is_dir() and any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()):
            entries[p.name] = sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            entries[p.stem] = p
    if not entries:
        raise BadInput(f"source {str(src)!r}: no per-camera image folders or videos")
    _check_cameras(list(entries), intr, f"source {str(src)!r}")
    fps = float(args.fps or _video_fps(entries) or DEFAULT_FPS)
    limit = args.frames or 10**9
    backend = args.backend or "mediapipe"
    est = _estimator(
        backend, frontend_options(backend, args.frontend_params), Rig([intr[c] for c in entries])
    )
    frames: dict[str, list[FrameDetections | None]] = {}
    images: dict[tuple[str, Path | int], Path] = {}
    for cam, what in entries.items():
        rect = Rectifier(intr[cam])
        seq: list[FrameDetections | None] = []
        for k, img in enumerate(_images(what, limit)):
            try:
                rect.check_size(img)
            except ValueError as e:
                raise BadInput(f"source {str(src)!r} camera {cam}: {' '.join(str(e).split())}") from None
            image = rect.rectify(img) if est.needs_image else None
            seq.append(_estimate(est, intr[cam], int(round(k * 1e9 / fps)), image, f"camera {cam} frame {k}"))
            if isinstance(what, list):  # image files can be overlaid in the report
                images[(cam, k)] = what[k]
        frames[cam] = seq
    return frames, fps, images  # type: ignore[return-value]  # fps set by the first camera


def _video_fps(entries: dict[str, list[Path] | Path]) -> float | None:
    import cv2

    for what in entries.values():
        if isinstance(what, Path):
            cap = cv2.VideoCapture(str(what))
            fps = cap.get(cv2.CAP_PROP_FPS) if cap.isOpened() else 0.0
            cap.release()
            if fps and np.isfinite(fps) and 1.0 <= fps <= 1000.0:
                return float(fps)
    return None


def _images(what: list[Path] | Path, limit: int) -> Iterator[np.ndarray]:
    import cv2

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


def save_detections(
    out: Path, frames: dict[str, list[FrameDetections | None]], fps: float, start_ns: int = 0
) -> None:
    """Write ``frames`` as a bag of ``/<cam>/detections`` (frame k stamped start + k / fps s),
    a SOURCE this tool reads back without running the backend again."""
    from maem_ros import bagio, wire

    if out.exists():
        raise BadInput(f"--save-detections {str(out)!r}: already exists")
    w = bagio.BagWriter(out)
    try:
        for cam, seq in frames.items():
            for k, d in enumerate(seq):
                if d is not None:
                    t = start_ns + int(round(k * 1e9 / fps))
                    d = d if d.stamp_ns == t else _restamped(d, t)
                    w.write(f"/{cam}/detections", wire.detections_to_msg(d), t)
    finally:
        w.close()


def _restamped(d: FrameDetections, stamp: int) -> FrameDetections:
    import dataclasses

    return dataclasses.replace(d, stamp_ns=stamp)
