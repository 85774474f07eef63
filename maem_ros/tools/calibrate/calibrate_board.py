"""maem-calibrate board: a rig (intrinsics, extrinsics) from images of a ChArUco or checkerboard.

    maem-calibrate board SOURCE --board charuco:7x5:0.12:0.09:DICT_4X4_50 --out rig.yaml
    maem-calibrate board SOURCE --board checkerboard:9x6:0.025 --out rig.yaml --intrinsics-only
    maem-calibrate board SOURCE --board ... --intrinsics known.yaml --out rig.yaml --format toml

SOURCE is one of:
  * a folder of per-camera image folders (camera = folder name; an ``images/`` folder inside
    SOURCE is looked into, as maem-sim writes it); images with the same trailing number in
    their names (000012.png in every camera) were taken at the same instant;
  * a folder of per-camera videos (camera = file stem; frame k of every video at one instant);
  * a rosbag2 folder with ``/<camera>/image_raw`` or ``/<camera>/image_raw/compressed``
    (frames whose stamps lie within 15 ms are one instant).
The algorithm is core.calibrate.board's. Extrinsics need frames that several cameras see
together; images taken one camera at a time give intrinsics only (said in one line).
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from maem_ros.core.calibrate.board import (
    JOINT_INTRINSICS,
    BoardSpec,
    CornerDetector,
    Detection,
    Intrinsics,
    NotSimultaneous,
    calibrate_extrinsics,
    calibrate_intrinsics,
)
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.geometry.rig_formats import write_pose2sim_toml

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")
#: bag frames of different cameras whose stamps lie within this are one instant, ns
BAG_SAME_INSTANT_NS = 15_000_000
#: views per camera given to cv2.calibrateCamera (evenly picked; more only cost time)
MAX_INTRINSIC_VIEWS = 40
PROG = "maem-calibrate board"


class SourceError(ValueError):
    """A SOURCE that cannot be read: one line naming it."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``board`` subcommand's arguments."""
    p.add_argument(
        "source",
        type=Path,
        help="folder of per-camera image folders or videos, or "
        "a rosbag2 folder with /<camera>/image_raw[/compressed]",
    )
    p.add_argument(
        "--board",
        required=True,
        help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT or "
        "checkerboard:COLSxROWS:SQUARE_M (COLSxROWS counts inner corners)",
    )
    p.add_argument("--out", required=True, type=Path, help="rig file to write")
    p.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="rig (any format maem reads) "
        "whose K, distortion and image size are used instead of calibrating them",
    )
    p.add_argument(
        "--intrinsics-only",
        action="store_true",
        help="calibrate intrinsics only (e.g. images taken one camera at a time)",
    )
    p.add_argument(
        "--format",
        choices=("yaml", "toml"),
        default=None,
        help="yaml: the rig YAML the nodes read; toml: a Pose2Sim/anipose Calib.toml "
        "(default: from --out's suffix, else yaml)",
    )
    p.add_argument("--step", type=int, default=1, help="use every STEP-th frame (default 1)")
    p.add_argument(
        "--k3",
        action="store_true",
        help="also estimate the k3 distortion term (wide-angle lenses; by default k3 = 0)",
    )
    p.add_argument(
        "--per-camera-intrinsics",
        action="store_true",
        help="without --intrinsics: keep each camera's own cv2.calibrateCamera "
        "intrinsics (default: refine them all in the joint bundle, from the shared "
        "frames; more accurate, doc/calibration_board.md)",
    )
    p.add_argument("--quiet", action="store_true", help="no per-camera summary")


@dataclass
class Frames:
    """Per camera: image size (w, h) and the detections by frame key (None: no board)."""

    sizes: dict[str, tuple[int, int]]
    detections: dict[str, dict[int, Detection | None]]


def _frame_number(stem: str) -> int | None:
    m = re.search(r"(\d+)$", stem)
    return int(m.group(1)) if m else None


def _image_folder_frames(folder: Path) -> Iterator[tuple[int, Path]]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    numbers = [_frame_number(p.stem) for p in files]
    if None in numbers or len(set(numbers)) != len(numbers):
        numbers = list(range(len(files)))  # no usable numbers: order only (not simultaneous)
    yield from zip(numbers, files)


def _read_gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise SourceError(f"image {str(path)!r}: unreadable")
    return img


def _images(source: Path) -> dict[str, Iterator[tuple[int, np.ndarray]]]:
    """camera -> (frame key, grayscale image) of a folder SOURCE."""
    root = source / "images" if (source / "images").is_dir() else source
    folders = sorted(
        p
        for p in root.iterdir()
        if p.is_dir() and any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir())
    )
    if folders:
        return {f.name: ((k, _read_gray(p)) for k, p in _image_folder_frames(f)) for f in folders}
    videos = sorted(p for p in root.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if videos:
        return {v.stem: _video_frames(v) for v in videos}
    raise SourceError(
        f"source {str(source)!r}: no per-camera image folders, videos or rosbag2 (metadata.yaml) found"
    )


def _video_frames(path: Path) -> Iterator[tuple[int, np.ndarray]]:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SourceError(f"video {str(path)!r}: cannot be opened")
    k = 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            yield k, cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            k += 1
    finally:
        cap.release()
    if k == 0:
        raise SourceError(f"video {str(path)!r}: no frames could be decoded")


def _bag_images(source: Path) -> dict[str, Iterator[tuple[int, np.ndarray]]]:
    """camera -> (frame key, grayscale image) of a bag's image topics; frame keys group stamps
    within BAG_SAME_INSTANT_NS of each other."""
    from maem_ros import bagio, wire

    info = bagio.bag_info(source)
    topics = {
        t: m
        for t, m in info.topics.items()
        if bagio.is_image_type(m) and re.fullmatch(r"/[^/]+/image_raw(/compressed)?", t)
    }
    if not topics:
        raise SourceError(f"bag {str(source)!r}: no /<camera>/image_raw[/compressed] topics")
    images: dict[str, list[tuple[int, np.ndarray]]] = {}
    for m in bagio.read_messages(source, topics):
        msg = m.decode()
        cam = m.topic.split("/")[1]
        bgr = (
            wire.compressed_to_bgr(msg, m.topic)
            if m.topic.endswith("/compressed")
            else wire.image_to_bgr(msg, m.topic)
        )
        images.setdefault(cam, []).append(
            (bagio.stamp_to_ns(msg.header.stamp), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        )
    stamps = sorted(s for frames in images.values() for s, _ in frames)
    keys, start, key = {}, None, -1
    for s in stamps:
        if start is None or s - start > BAG_SAME_INSTANT_NS:
            start, key = s, key + 1
        keys[s] = key
    return {cam: iter([(keys[s], img) for s, img in frames]) for cam, frames in images.items()}


def detect_source(source: Path, spec: BoardSpec, step: int = 1) -> Frames:
    """Detect the board in every (step-th) frame of every camera of SOURCE."""
    if not source.exists():
        raise SourceError(f"source {str(source)!r}: no such file or folder")
    if not source.is_dir():
        raise SourceError(
            f"source {str(source)!r}: expected a folder (image folders, videos or a rosbag2 folder)"
        )
    streams = _bag_images(source) if (source / "metadata.yaml").is_file() else _images(source)
    detector = CornerDetector(spec)
    sizes: dict = {}
    detections: dict = {}
    for cam, frames in streams.items():
        detections[cam] = {}
        for n, (key, gray) in enumerate(frames):
            if n % step:
                continue
            size = (gray.shape[1], gray.shape[0])
            if sizes.setdefault(cam, size) != size:
                raise SourceError(
                    f"camera {cam!r}: image size {size[0]}x{size[1]} at frame {key} "
                    f"differs from {sizes[cam][0]}x{sizes[cam][1]}"
                )
            detections[cam][key] = detector(gray)
    return Frames(sizes, detections)


def _spread(items: list, n: int) -> list:
    """At most ``n`` of ``items``, evenly picked."""
    if len(items) <= n:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def intrinsics_of(
    frames: Frames, spec: BoardSpec, known: Rig | None, k3: bool = False
) -> dict[str, Intrinsics]:
    """Per camera: the given intrinsics (``known``) or cv2.calibrateCamera's."""
    out = {}
    for cam, dets in frames.detections.items():
        if known is not None:
            if cam not in known:
                raise SourceError(f"--intrinsics: no camera {cam!r} (it has {known.names})")
            c = known[cam]
            if (c.width, c.height) != frames.sizes[cam]:
                raise SourceError(
                    f"--intrinsics camera {cam!r}: {c.width}x{c.height} px, its images "
                    f"are {frames.sizes[cam][0]}x{frames.sizes[cam][1]}"
                )
            if c.distortion_model != "plumb_bob":
                raise SourceError(
                    f"--intrinsics camera {cam!r}: {c.distortion_model} distortion "
                    f"is not supported by the board mode (plumb_bob only)"
                )
            out[cam] = Intrinsics(c.K, c.D, c.width, c.height, float("nan"), 0)
            continue
        views = _spread([d for d in dets.values() if d is not None], MAX_INTRINSIC_VIEWS)
        out[cam] = calibrate_intrinsics(views, spec, frames.sizes[cam], cam, k3=k3)
    return out


def _cameras(intr: dict[str, Intrinsics], ext=None) -> list[Camera]:
    """Cameras of the calibration (without extrinsics: R = I, t = 0 placeholders, which the
    YAML writer leaves out)."""
    return [
        Camera(
            name,
            i.K,
            np.eye(3) if ext is None else ext.R[c],
            np.zeros(3) if ext is None else ext.t[c],
            i.width,
            i.height,
            "plumb_bob",
            i.D,
        )
        for c, (name, i) in enumerate(intr.items())
    ]


def write_rig(path: Path, cameras: list[Camera], fmt: str, extrinsics: bool, error_px: float | None) -> None:
    """YAML (intrinsics only without extrinsics) or Pose2Sim TOML (placeholder zero poses)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "toml":
        write_pose2sim_toml(path, cameras, error_px)
    else:
        Rig(cameras).to_yaml(path, extrinsics=extrinsics)


def _summary(intr: dict[str, Intrinsics], ext, names: list[str]) -> list[str]:
    lines = []
    for c, name in enumerate(names):
        i = intr[name]
        line = (
            f"  {name}: fx {i.K[0, 0]:.2f} fy {i.K[1, 1]:.2f} cx {i.K[0, 2]:.2f} "
            f"cy {i.K[1, 2]:.2f} px, k1 {i.D[0]:+.4f} k2 {i.D[1]:+.4f}"
        )
        line += f", RMS {i.rms:.3f} px over {i.views} views ({i.dropped} dropped)" if i.views else " (given)"
        line += " (refined in the joint bundle)" if i.joint else ""
        if ext is not None:
            e = ext.errors[c]
            line += (
                f"; extrinsics from {ext.frames_per_camera[c]} frames, reprojection median "
                f"{np.median(e):.3f} p90 {np.percentile(e, 90):.3f} px"
                if e.size
                else "; no board corners in the bundle adjustment"
            )
        lines.append(line)
    return lines


def run(args: argparse.Namespace) -> int:
    """Run ``maem-calibrate board`` (parsed arguments); exit code."""
    fmt = args.format or ("toml" if args.out.suffix.lower() == ".toml" else "yaml")
    try:
        if args.step < 1:
            raise SourceError(f"--step: must be >= 1, got {args.step}")
        spec = BoardSpec.parse(args.board)
        try:
            known = Rig.load_intrinsics(args.intrinsics) if args.intrinsics else None
        except ValueError as e:
            raise SourceError(f"--intrinsics: {e}") from None
        frames = detect_source(args.source, spec, args.step)
        intr = intrinsics_of(frames, spec, known, args.k3)
        names = list(intr)
        ext = None
        if not args.intrinsics_only:
            if len(names) < 2:
                print(
                    f"{PROG}: one camera ({names[0]}): extrinsics need two or more; writing intrinsics only"
                )
            else:
                try:
                    dets = {
                        (c, k): d
                        for c, n in enumerate(names)
                        for k, d in frames.detections[n].items()
                        if d is not None
                    }
                    # intrinsics calibrated here (not given) start the joint refinement
                    joint = (
                        ()
                        if known is not None or args.per_camera_intrinsics
                        else JOINT_INTRINSICS + (("k3",) if args.k3 else ())
                    )
                    ext = calibrate_extrinsics(
                        spec, dets, [(intr[n].K, intr[n].D) for n in names], names, joint
                    )
                    if joint:
                        for c, n in enumerate(names):
                            intr[n] = replace(intr[n], K=ext.K[c], D=ext.D[c], joint=True)
                except NotSimultaneous as e:
                    print(f"{PROG}: {e}; writing intrinsics only")
        cameras = _cameras(intr, ext)
        errors = np.concatenate(ext.errors) if ext is not None else np.zeros(0)
        rms = float(np.sqrt(np.mean(errors**2))) if errors.size else None
        write_rig(args.out, cameras, fmt, ext is not None, rms)
    except (ValueError, OSError) as e:  # SourceError, bad board / rig / bag: one line
        print(f"{PROG}: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        found = {n: sum(d is not None for d in frames.detections[n].values()) for n in names}
        print(
            f"{PROG}: board {spec} found in "
            + ", ".join(f"{n} {found[n]}/{len(frames.detections[n])}" for n in names)
        )
        for line in _summary(intr, ext, names):
            print(line)
    what = "rig" if ext is not None else "intrinsics only"
    print(f"{PROG}: {what} of {len(names)} cameras -> {str(args.out)!r} ({fmt})")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog=PROG, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
