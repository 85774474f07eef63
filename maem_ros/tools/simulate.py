"""maem-sim: write a synthetic scene folder (cameras/, dets/, gt.npz, scene.json, optional images/).

maem-sim OUT --rig sportcenter6 --frames 90 --difficulty medium --seed 0 [--images] [--vertices N]
         [--time-offset CAM=S ...] [--intrinsics-only]
maem-sim OUT --rig lab4 --board charuco:7x5:0.15:0.11:DICT_4X4_50 --frames 20 [--board-per-camera]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from maem_ros.core.interchange import SceneFolder
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.tools.cli import fail

EPILOG = """\
Output layout:
  OUT/cameras/<view>.json          MAEM camera JSON per view (world->camera; with --intrinsics-only
                                   K, distortion and size only, for calibration tests)
  OUT/gt_rig.yaml                  the true rig (extrinsics, time_offset per camera)
  OUT/dets/<view>/<frame:06d>.npz  simulated SAM 3D Body outputs, MAEM authors' npz, RAW (distorted) px
  OUT/gt.npz                       ground truth, xrmocap keypoints3d, sportcenter_13 (see below)
  OUT/det_ids.npz                  GT person of every detection: key "<view>/<frame:06d>", (N,) int64
                                   in the npz's detection order; the scene's person index (players
                                   first: index p < players is gt.npz person p), -1 = false positive
  OUT/images/<view>/<frame:06d>.jpg  raw rendered images (with --images)
  OUT/scene.json                   fps, start_stamp_ns, num_frames, scene_config (regenerates the scene)
With --board: a calibration-board sequence instead of people (sim/board.py):
  OUT/images/<view>/<frame:06d>.png  raw grayscale images of the board, through each lens
  OUT/board.npz                    spec, board -> world poses R (F,3,3), t (F,3), camera (F,)
  OUT/gt_rig.yaml, OUT/cameras/    the true rig; camera JSONs (intrinsics only unless
                                   --with-extrinsics)
By default ground truth holds the players (is_player): referees/bystanders are distractors
(mostly low-score detections), so triangulating one counts as a false positive in AP; with
--gt-people all they are ground truth too.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-sim",
        description=__doc__.splitlines()[0],
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", type=Path, help="scene folder to write (created; existing files overwritten)")
    p.add_argument(
        "--rig", default="sportcenter6", help="shipped rig name or rig file (default sportcenter6)"
    )
    p.add_argument("--frames", type=int, default=90, help="number of frames (default 90)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    p.add_argument(
        "--difficulty",
        default="medium",
        choices=("none", "easy", "medium", "hard"),
        help="detection-noise preset (none = exact, for tests)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--vertices",
        type=int,
        default=None,
        help="mesh vertices per detection (default: the simulator's, 18439)",
    )
    p.add_argument(
        "--gt-people",
        choices=("players", "all"),
        default="players",
        help="who gt.npz holds: players (default; referees/bystanders are distractors) or all",
    )
    p.add_argument("--images", action="store_true", help="also render raw JPEG images")
    p.add_argument(
        "--time-offset",
        action="append",
        default=[],
        metavar="CAM=S",
        help="camera CAM captures each frame S seconds after its stamp (it samples the "
        "motion at its own time; |S| < 0.9; written as time_offset into the rig); "
        "repeat per camera",
    )
    p.add_argument(
        "--board",
        default=None,
        metavar="SPEC",
        help="render a calibration-board sequence instead of people: "
        "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT or checkerboard:COLSxROWS:SQUARE_M "
        "(--frames board poses; use a room-sized rig such as lab4)",
    )
    p.add_argument(
        "--board-per-camera",
        action="store_true",
        help="with --board: --frames poses per camera, each seen by that camera only "
        "(photographed one camera at a time)",
    )
    p.add_argument(
        "--with-extrinsics",
        action="store_true",
        help="with --board: cameras/ holds the full rig, not intrinsics only",
    )
    p.add_argument(
        "--intrinsics-only",
        action="store_true",
        help="cameras/ holds intrinsics only (no extrinsics), for calibration tests; "
        "the true rig is in gt_rig.yaml",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def scene_config(args: argparse.Namespace):
    from ..sim.scene import SceneConfig

    cfg = SceneConfig().to_dict()
    cfg.update(rig=args.rig, frames=args.frames, fps=args.fps, difficulty=args.difficulty, seed=args.seed)
    if args.vertices is not None:
        cfg["num_vertices"] = args.vertices
    cfg["time_offsets"] = parse_time_offsets(args.time_offset)
    return SceneConfig.from_dict(cfg)


def parse_time_offsets(items: Sequence[str]) -> dict[str, float]:
    """["camera_1=0.04", ...] -> {"camera_1": 0.04}; ValueError naming a malformed item."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            out[name] = float(value)
        except ValueError:
            sep = ""
        if not sep or not name:
            raise ValueError(f"--time-offset {item!r}: expected CAMERA=SECONDS")
    return out


def gt_arrays(scene, frames: int, people: str = "players") -> tuple[np.ndarray, np.ndarray]:
    """(F,P,13,3) world metres, (F,P,13) mask (all True: the sim knows every joint).

    ``people``: "players" (the is_player persons) or "all" (referees/bystanders too).
    """
    keep = np.asarray(scene.is_player, dtype=bool) if people == "players" else slice(None)
    pose = np.stack([SPORTCENTER_13.select(np.asarray(scene.gt_keypoints(f))[keep]) for f in range(frames)])
    return pose, np.ones(pose.shape[:3], dtype=bool)


def write_scene(
    out: Path,
    config,
    images: bool = False,
    progress: bool = True,
    gt_people: str = "players",
    intrinsics_only: bool = False,
) -> SceneFolder:
    """Simulate ``config`` and write the scene folder ``out`` (``intrinsics_only``: cameras/
    without extrinsics; the true rig is always in gt_rig.yaml)."""
    from ..sim.scene import Scene

    scene = Scene(config)
    n = scene.num_frames
    info = {
        "fps": float(config.fps),
        "start_stamp_ns": int(scene.stamp_ns(0)),
        "num_frames": int(n),
        "gt_people": gt_people,
        "scene_config": config.to_dict(),
    }
    folder = SceneFolder.create(out, scene.rig, info, extrinsics=not intrinsics_only)
    scene.rig.to_yaml(Path(out) / "gt_rig.yaml")
    ids = {}
    for frame in tqdm(range(n), desc="maem-sim", unit="frame", disable=not progress):
        for cam in scene.rig.names:
            folder.write_outputs(cam, frame, scene.raw_outputs(cam, frame))
            ids[cam, frame] = scene.detection_persons(cam, frame)
            if images:
                folder.write_image(cam, frame, scene.render(cam, frame))
    folder.write_gt(*gt_arrays(scene, n, gt_people), convention=SPORTCENTER_13.name)
    folder.write_det_ids(ids)
    return folder


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames < 1:
        return fail("maem-sim", "--frames must be >= 1")
    if args.vertices is not None and args.vertices < 1:
        return fail("maem-sim", "--vertices must be >= 1")
    if args.board:
        return write_board(args)
    try:
        config = scene_config(args)
        write_scene(
            args.out,
            config,
            images=args.images,
            progress=not args.quiet,
            gt_people=args.gt_people,
            intrinsics_only=args.intrinsics_only,
        )
    except ValueError as e:
        return fail("maem-sim", e)
    views = len(list((args.out / "cameras").glob("*.json")))
    print(f"maem-sim: wrote {config.frames} frames x {views} views to {str(args.out)!r}")
    return 0


def write_board(args: argparse.Namespace) -> int:
    """maem-sim --board: render and write a board sequence (exit code)."""
    from ..core.calibrate.board import BoardSpec
    from ..sim.board import board_poses, write_board_sequence
    from ..sim.rigs import load_rig

    try:
        spec = BoardSpec.parse(args.board)
        rig = load_rig(args.rig)
        poses = board_poses(rig, spec, args.frames, args.seed, per_camera=args.board_per_camera)
        write_board_sequence(args.out, rig, spec, poses, args.seed, intrinsics_only=not args.with_extrinsics)
    except ValueError as e:
        return fail("maem-sim", e)
    print(f"maem-sim: wrote {len(poses.R)} board poses of {spec} x {len(rig)} views to {str(args.out)!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
