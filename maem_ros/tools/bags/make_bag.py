"""maem-make-bag: build a rosbag2 (MCAP) bag from dataset frames or a maem-sim scene folder.

    maem-make-bag OUT --frames-dir DIR --rig RIG --fps F [--dets DIR] [--gt gt.npz] [--start-stamp NS]
    maem-make-bag OUT --videos DIR --rig CALIB [--fps F] [--jpeg-quality Q] [--start-stamp NS]
    maem-make-bag OUT --scene SCENE_DIR

Per camera <cam> of the rig and frame k (stamp = start + round(k * 1e9 / fps) ns, also the bag
log time): /<cam>/camera_info, /<cam>/image_raw/compressed (the image file's bytes unchanged,
format "jpeg"/"png"; from --videos, frame k of
<cam>.mp4|avi|mov|mkv decoded and JPEG-encoded at --jpeg-quality), /<cam>/detections (MAEM npz
-> rectified detections, doc/design.md §4 layout);
per frame /maem/gt_poses (Poses layout, id = GT person index, NaN = masked joint, views 0,
score 1). A scene folder adds its scene.json as a latched /maem/scene std_msgs/String at the first
stamp and in metadata custom_data (``maem.scene``); the rig YAML is stored as ``maem.rig``.
--rig takes a rig YAML, a folder of MAEM camera JSONs, a Qualisys .qca.txt, a Pose2Sim Calib*.toml
or a shipped rig name; video files are matched to its camera names by file stem, and every
video frame must have the calibration's size (a rotated or rescaled video is an error, exit 2).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from maem_ros import bagio, wire
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.core.geometry.frames import rig_transforms
from maem_ros.core.interchange import SceneFolder, outputs_to_detections, read_gt, read_maem_npz
from maem_ros.tools.cli import fail

DEFAULT_START_NS = 1_700_000_000_000_000_000
IMAGE_FORMATS = {".jpg": "jpeg", ".jpeg": "jpeg", ".png": "png"}
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
DEFAULT_JPEG_QUALITY = 90
GT_FRAME_ID = "world"


def warn(text: str) -> None:
    """One-line message on stderr that does not break the progress bar."""
    tqdm.write(f"maem-make-bag: {text}", file=sys.stderr)


def natural_key(s: str) -> list:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]


@dataclass
class Sources:
    """Everything make_bag reads: frames (stems in order), per-camera image files, dets folder."""

    rig: Rig
    fps: float
    start_ns: int
    frames: list[str]  # frame stems, frame index = position
    images: dict[str, dict[str, Path]]  # camera -> stem -> image file
    dets_dir: Path | None = None
    gt_path: Path | None = None
    scene: dict | None = None
    videos: dict[str, Path] = field(default_factory=dict)  # camera -> video file


@dataclass
class Report:
    """Skipped items, summarised at the end (one line per kind and camera)."""

    skipped: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))

    def skip(self, kind: str, item: str) -> None:
        self.skipped[kind].append(item)

    def lines(self) -> list[str]:
        out = []
        for kind, items in self.skipped.items():
            shown = ", ".join(items[:3]) + (f", ... (+{len(items) - 3})" if len(items) > 3 else "")
            out.append(f"skipped {len(items)} x {kind}: {shown}")
        return out


# ---- inputs ----------------------------------------------------------------------------------
def image_folders(frames_dir: Path, rig: Rig, report: Report) -> dict[str, dict[str, Path]]:
    """camera -> {stem: file} for every <view>/ folder with images; folders not in the rig skipped."""
    out: dict[str, dict[str, Path]] = {}
    for sub in sorted((p for p in frames_dir.iterdir() if p.is_dir()), key=lambda p: natural_key(p.name)):
        files = {
            f.stem: f
            for f in sorted(sub.iterdir(), key=lambda f: natural_key(f.name))
            if f.is_file() and f.suffix.lower() in IMAGE_FORMATS
        }
        if not files:
            continue
        if sub.name not in rig:
            warn(
                f"image folder {str(sub)!r}: camera {sub.name!r} has no calibration in the rig "
                f"(known: {rig.names}); skipped"
            )
            report.skip("camera without calibration", sub.name)
            continue
        out[sub.name] = files
    return out


def frame_stems(images: dict[str, dict[str, Path]]) -> list[str]:
    """Natural-sorted union of image stems over cameras."""
    return sorted({s for files in images.values() for s in files}, key=natural_key)


def sources_from_frames(
    frames_dir: Path,
    rig_path: str,
    fps: float,
    start_ns: int,
    dets: Path | None,
    gt: Path | None,
    report: Report,
) -> Sources:
    if not frames_dir.is_dir():
        raise ValueError(f"--frames-dir {str(frames_dir)!r}: no such folder")
    rig = Rig.load(rig_path)
    images = image_folders(frames_dir, rig, report)
    if not images:
        raise ValueError(
            f"--frames-dir {str(frames_dir)!r}: no <camera>/*.jpg|png folder matching "
            f"the rig's cameras {rig.names}"
        )
    return Sources(rig, fps, start_ns, frame_stems(images), images, dets, gt)


def sources_from_scene(root: Path, report: Report) -> Sources:
    """A maem-sim scene folder (core.interchange.SceneFolder: same fps, stamps and frame count)."""
    folder = SceneFolder(root)
    images = image_folders(root / "images", folder.rig, report) if (root / "images").is_dir() else {}
    num = folder.num_frames
    if not num and images:
        num = max(
            (int(m.group(1)) + 1 for s in frame_stems(images) if (m := re.search(r"(\d+)$", s))), default=0
        )
    if num == 0:
        raise ValueError(f"--scene {str(root)!r}: no frames (no scene.json num_frames, images or dets)")
    return Sources(
        folder.rig,
        folder.fps,
        folder.start_stamp_ns,
        [f"{k:06d}" for k in range(num)],
        images,
        root / "dets" if (root / "dets").is_dir() else None,
        root / "gt.npz" if folder.has_gt else None,
        folder.info or None,
    )


def video_files(videos_dir: Path, rig: Rig, report: Report) -> dict[str, Path]:
    """camera -> <camera>.mp4|avi|mov|mkv in ``videos_dir``; videos not in the rig skipped."""
    out: dict[str, Path] = {}
    for f in sorted(videos_dir.iterdir(), key=lambda f: natural_key(f.name)):
        if not (f.is_file() and f.suffix.lower() in VIDEO_SUFFIXES):
            continue
        if f.stem not in rig:
            warn(
                f"video {str(f)!r}: camera {f.stem!r} has no calibration in the rig "
                f"(known: {rig.names}); skipped"
            )
            report.skip("video without calibration", f.name)
        elif f.stem in out:
            raise ValueError(
                f"--videos {str(videos_dir)!r}: two videos for camera {f.stem!r} "
                f"({out[f.stem].name}, {f.name})"
            )
        else:
            out[f.stem] = f
    return out


class VideoReader:
    """Sequential frames of one camera's video, checked against its calibrated size."""

    def __init__(self, path: Path, camera: Camera):
        self.path, self.camera = path, camera
        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise ValueError(f"video {str(path)!r}: cannot be opened (not a video OpenCV decodes)")
        self.frames = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS))
        w = int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (w, h) != (camera.width, camera.height):
            self.cap.release()
            raise ValueError(
                f"video {str(path)!r}: frames are {w}x{h} but camera "
                f"{camera.name!r} is calibrated at {camera.width}x{camera.height}"
            )

    def read(self) -> np.ndarray | None:
        """The next frame (BGR), None at the end or when it cannot be decoded."""
        ok, frame = self.cap.read()
        return frame if ok else None

    def close(self) -> None:
        self.cap.release()


def sources_from_videos(
    videos_dir: Path, rig_path: str, fps: float | None, start_ns: int, report: Report
) -> Sources:
    """One video per rig camera; frame k of every video is frame k of the bag."""
    if not videos_dir.is_dir():
        raise ValueError(f"--videos {str(videos_dir)!r}: no such folder")
    rig = Rig.load(rig_path)
    videos = video_files(videos_dir, rig, report)
    if not videos:
        raise ValueError(
            f"--videos {str(videos_dir)!r}: no <camera>{'|'.join(VIDEO_SUFFIXES)} "
            f"named after the rig's cameras {rig.names}"
        )
    readers = [VideoReader(path, rig[cam]) for cam, path in videos.items()]
    for r in readers:
        r.close()
    rates = {r.path.name: r.fps for r in readers}
    if fps is None:
        good = [f for f in rates.values() if f > 0]
        if not good:
            raise ValueError(f"--videos {str(videos_dir)!r}: the videos give no frame rate; pass --fps")
        fps = float(np.median(good))
    if any(f > 0 and abs(f - fps) > 0.01 * fps for f in rates.values()):
        warn(
            f"video frame rates {rates} differ from the bag's {fps:g} fps; frame k of every "
            f"video gets stamp start + k / {fps:g} s"
        )
    num = max(r.frames for r in readers)
    if num <= 0:
        raise ValueError(f"--videos {str(videos_dir)!r}: the videos report no frames")
    return Sources(rig, fps, start_ns, [f"{k:06d}" for k in range(num)], {}, videos=videos)


# ---- per-message helpers ---------------------------------------------------------------------
def stamp_ns(start_ns: int, fps: float, k: int) -> int:
    """Frame k's stamp (same rounding as SceneFolder.stamp_ns)."""
    return int(start_ns) + int(round(k * 1e9 / fps))


def readable_image(path: Path) -> tuple[bytes | None, str]:
    """(file bytes, format) or (None, reason) when the image cannot be decoded."""
    try:
        data = path.read_bytes()
    except OSError as e:
        return None, f"unreadable ({e.strerror})"
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    if img is None:
        return None, "not a decodable image"
    return data, IMAGE_FORMATS[path.suffix.lower()]


def vertex_subset(num_vertices: int, keep: int) -> np.ndarray | None:
    """Evenly spaced vertex indices (the same subset for every camera), None = keep all."""
    if keep <= 0 or keep >= num_vertices:
        return None
    return np.unique(np.linspace(0, num_vertices - 1, keep).round().astype(np.int64))


def detections_message(path: Path, camera: Camera, stamp: int, max_vertices: int):
    """PointCloud2 of one npz (rectified detections, doc/design.md §4 layout)."""
    dets = outputs_to_detections(read_maem_npz(path), camera, stamp, where=f"npz {str(path)!r} outputs")
    idx = vertex_subset(dets.num_vertices, max_vertices)
    if idx is not None:
        dets.verts2d = np.ascontiguousarray(dets.verts2d[:, idx])
    return wire.detections_to_msg(dets)


def gt_message(pose: np.ndarray, mask: np.ndarray, stamp: int):
    """GT of one frame (P,K,4|3), mask (P,K) -> Poses PointCloud2 (persons with >= 1 valid joint)."""
    mask = np.asarray(mask, bool) & np.all(np.isfinite(pose[..., :3]), axis=-1)
    keep = np.flatnonzero(mask.any(axis=1))
    joints = np.where(mask[keep, :, None], pose[keep, :, :3], np.nan)
    return wire.poses_to_msg(
        stamp, GT_FRAME_ID, keep, joints, np.zeros(len(keep), np.int64), np.ones(len(keep))
    )


def find_dets_file(dets_dir: Path, cam: str, stem: str, k: int) -> Path | None:
    for name in (f"{stem}.npz", f"{k:06d}.npz"):
        if (dets_dir / cam / name).is_file():
            return dets_dir / cam / name
    return None


def rig_yaml(rig: Rig) -> str:
    return yaml.safe_dump(
        {"cameras": {c.name: c.to_dict() for c in rig}}, sort_keys=False, default_flow_style=None
    )


# ---- writing ---------------------------------------------------------------------------------
def active_cameras(src: Sources, report: Report) -> list[str]:
    """Rig cameras with images or detections; the others are reported and skipped."""
    cams = []
    for cam in src.rig.names:
        has_dets = src.dets_dir is not None and (src.dets_dir / cam).is_dir()
        if cam in src.images or cam in src.videos or has_dets:
            cams.append(cam)
        else:
            report.skip("rig camera without images or detections", cam)
    if src.dets_dir is not None:
        for sub in sorted(p.name for p in src.dets_dir.iterdir() if p.is_dir()):
            if sub not in src.rig:
                report.skip("detections folder for a camera not in the rig", sub)
    return cams


def load_gt(src: Sources, report: Report) -> tuple[np.ndarray, np.ndarray, str] | None:
    if src.gt_path is None:
        return None
    pose, mask, convention = read_gt(src.gt_path)
    if pose.shape[0] != len(src.frames):
        warn(
            f"gt {str(src.gt_path)!r}: {pose.shape[0]} frames, the images have {len(src.frames)}; "
            "GT frame k goes with image frame k"
        )
        for k in range(pose.shape[0], len(src.frames)):
            report.skip("frame without ground truth", src.frames[k])
    return pose, mask, convention


def video_frame_message(reader: VideoReader, t: int, quality: int, stem: str, report: Report):
    """The reader's next frame as a JPEG CompressedImage, None (reported) past its end."""
    frame = reader.read()
    if frame is None:
        report.skip(f"missing video frame of camera {reader.camera.name}", stem)
        return None
    try:
        return wire.bgr_to_compressed(frame, t, reader.camera.name, quality)
    except ValueError as e:
        raise ValueError(f"video {str(reader.path)!r} frame {stem}: {e}") from None


def write_frame(
    w: bagio.BagWriter,
    src: Sources,
    cams: Sequence[str],
    k: int,
    gt,
    opts,
    report: Report,
    readers: dict[str, VideoReader] | None = None,
) -> None:
    """All messages of frame k: per camera camera_info, image, detections; then GT."""
    stem, t = src.frames[k], stamp_ns(src.start_ns, src.fps, k)
    for cam in cams:
        camera = src.rig[cam]
        msgs = []
        if readers and cam in readers:
            msg = video_frame_message(readers[cam], t, opts.jpeg_quality, stem, report)
            if msg is not None:
                msgs.append((f"/{cam}/image_raw/compressed", msg))
        img = src.images.get(cam, {}).get(stem)
        if cam in src.images:
            if img is None:
                report.skip(f"missing image of camera {cam}", stem)
            else:
                data, fmt = readable_image(img)
                if data is None:
                    warn(f"image {str(img)!r}: {fmt}; skipped")
                    report.skip("unreadable image", str(img))
                else:
                    msgs.append(
                        (f"/{cam}/image_raw/compressed", wire.compressed_image_msg(data, fmt, t, cam))
                    )
        if src.dets_dir is not None and (src.dets_dir / cam).is_dir():
            path = find_dets_file(src.dets_dir, cam, stem, k)
            if path is None:
                report.skip(f"missing detections of camera {cam}", stem)
            else:
                try:
                    msgs.append(
                        (f"/{cam}/detections", detections_message(path, camera, t, opts.max_vertices))
                    )
                except ValueError as e:
                    warn(f"{e}; skipped")
                    report.skip("bad detections file", str(path))
        if msgs:
            w.write(f"/{cam}/camera_info", wire.camera_info_msg(camera, t, cam), t)
            for topic, msg in msgs:
                w.write(topic, msg, t)
    if gt is not None and k < gt[0].shape[0]:
        w.write(bagio.GT_TOPIC, gt_message(gt[0][k], gt[1][k], t), t)


def make_bag(out: Path, src: Sources, opts, report: Report) -> bagio.BagWriter:
    """Write the bag; returns the (closed) writer with per-topic counts."""
    cams = active_cameras(src, report)
    if not cams:
        raise ValueError("no camera has both a calibration and images or detections")
    gt = load_gt(src, report)
    readers = {cam: VideoReader(path, src.rig[cam]) for cam, path in src.videos.items() if cam in cams}
    w = bagio.BagWriter(out, compress=opts.compress)
    try:
        w.set_custom(bagio.CUSTOM_RIG, rig_yaml(src.rig))
        if gt is not None:
            w.set_custom(bagio.CUSTOM_GT_CONVENTION, gt[2])
        if src.scene is not None:
            text = json.dumps(src.scene, sort_keys=True)
            w.set_custom(bagio.CUSTOM_SCENE, text)
            w.write(bagio.SCENE_TOPIC, bagio.string_msg(text), src.start_ns, bagio.QOS_LATCHED)
        # world -> each camera, latched, so TF users (RViz, Foxglove) place the cameras
        tf = [t for t in rig_transforms(src.rig) if t.child in cams]
        w.write(
            wire.TF_STATIC_TOPIC,
            wire.tf_message(tf, src.start_ns, bagio.TYPESTORE.types),
            src.start_ns,
            bagio.QOS_LATCHED,
        )
        for k in tqdm(range(len(src.frames)), desc="maem-make-bag", unit="frame", disable=opts.quiet):
            write_frame(w, src, cams, k, gt, opts, report, readers)
    finally:
        w.close()
        for r in readers.values():
            r.close()
    return w


# ---- CLI -------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-make-bag",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog=__doc__.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", type=Path, help="output bag folder (must not exist)")
    p.add_argument(
        "--scene",
        type=Path,
        help="maem-sim scene folder (uses its cameras/, images/, dets/, gt.npz, scene.json)",
    )
    p.add_argument("--frames-dir", type=Path, help="folder of <camera>/*.jpg|png image folders")
    p.add_argument(
        "--videos",
        type=Path,
        help="folder of one video per camera, <camera>.mp4|avi|mov|mkv (camera = name in --rig)",
    )
    p.add_argument(
        "--rig",
        help="rig YAML, folder of MAEM camera JSONs, Qualisys .qca.txt, "
        "Pose2Sim Calib*.toml, or shipped rig name",
    )
    p.add_argument(
        "--fps",
        type=float,
        help="frame rate for the stamps (frame k at start + k/fps; with --videos default: the videos' rate)",
    )
    p.add_argument(
        "--jpeg-quality",
        type=int,
        default=DEFAULT_JPEG_QUALITY,
        metavar="Q",
        help=f"JPEG quality of --videos frames (default {DEFAULT_JPEG_QUALITY})",
    )
    p.add_argument("--dets", type=Path, help="MAEM npz folder dets/<camera>/<frame>.npz")
    p.add_argument("--gt", type=Path, help="xrmocap keypoints3d gt.npz (row k = frame k)")
    p.add_argument(
        "--start-stamp",
        type=int,
        default=None,
        metavar="NS",
        help=f"stamp of frame 0 in ns (default {DEFAULT_START_NS})",
    )
    p.add_argument(
        "--max-vertices",
        type=int,
        default=0,
        metavar="N",
        help="keep N evenly spaced mesh vertices per detection (default all)",
    )
    p.add_argument("--compress", action="store_true", help="zstd MCAP chunk compression")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def resolve_sources(a: argparse.Namespace, p: argparse.ArgumentParser, report: Report) -> Sources:
    if a.scene is not None:
        if a.frames_dir or a.videos or a.rig or a.fps or a.start_stamp is not None:
            p.error(
                "--scene takes frames, rig, fps and stamps from the scene folder; do not combine "
                "it with --frames-dir/--rig/--fps/--start-stamp"
            )
        src = sources_from_scene(a.scene, report)
        src.dets_dir = a.dets or src.dets_dir
        src.gt_path = a.gt or src.gt_path
        return src
    from maem_ros.params import resolve_rig_path

    if a.fps is not None and not a.fps > 0:
        p.error(f"--fps: must be > 0, got {a.fps}")
    if a.videos is not None:
        if a.frames_dir or a.dets or a.gt:
            p.error(
                "--videos takes the images from the videos; do not combine it with --frames-dir/--dets/--gt"
            )
        if not a.rig:
            p.error("--videos needs --rig (the calibration whose camera names the videos carry)")
        if not 1 <= a.jpeg_quality <= 100:
            p.error(f"--jpeg-quality: must be 1..100, got {a.jpeg_quality}")
        return sources_from_videos(
            a.videos,
            str(resolve_rig_path(a.rig)),
            a.fps,
            DEFAULT_START_NS if a.start_stamp is None else a.start_stamp,
            report,
        )
    if not (a.frames_dir and a.rig and a.fps):
        p.error("give --scene DIR, --videos DIR and --rig, or --frames-dir, --rig and --fps")
    return sources_from_frames(
        a.frames_dir,
        str(resolve_rig_path(a.rig)),
        a.fps,
        DEFAULT_START_NS if a.start_stamp is None else a.start_stamp,
        a.dets,
        a.gt,
        report,
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    report = Report()
    if a.out.exists():
        return fail("maem-make-bag", f"output {str(a.out)!r} exists already; not overwriting")
    for opt in ("dets", "gt"):
        path = getattr(a, opt)
        if path is not None and not path.exists():
            return fail("maem-make-bag", f"--{opt} {str(path)!r}: no such file or folder")
    if a.start_stamp is not None and a.start_stamp < 0:
        p.error(f"--start-stamp: must be >= 0, got {a.start_stamp}")
    try:
        src = resolve_sources(a, p, report)
        w = make_bag(a.out, src, a, report)
    except ValueError as e:
        return fail("maem-make-bag", e)
    for line in report.lines():
        print(f"maem-make-bag: {line}", file=sys.stderr)
    data_msgs = sum(n for t, n in w.counts.items() if t.endswith(("/compressed", "/detections")))
    print(
        f"maem-make-bag: wrote {w.message_count} messages ({len(src.frames)} frames, "
        f"{len([t for t in w.counts if t.endswith('/camera_info')])} cameras) to {str(a.out)!r}"
    )
    if data_msgs == 0:
        return fail("maem-make-bag", "no image or detection could be written", 1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
