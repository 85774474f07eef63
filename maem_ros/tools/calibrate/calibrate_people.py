"""``maem-calibrate people``: calibrate a rig from the players (extrinsics, floor, scale, time).

SOURCE is a MAEM scene folder (``dets/<cam>/*.npz``), a bag with ``/<cam>/detections``, or a
folder of per-camera image folders / videos (``<cam>/*.jpg`` or ``<cam>.mp4``) run through a
frontend backend (reading them: tools/calibrate_sources.py). ``--intrinsics`` gives K,
distortion and image size (any rig format the project reads; extrinsics there are ignored).
Writes the rig (YAML, or Pose2Sim TOML with
``--format toml``), prints a per-camera summary, with ``--report DIR`` draws pictures, and
with ``--reference RIG`` prints the errors against a reference rig.
How-to: doc/calibration.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from maem_ros.core.calibrate.timing_joint import TIME_METHODS, TIME_TESTS
from maem_ros.core.geometry.camera import Rig
from maem_ros.tools.calibrate.calibrate_sources import BadInput, load_source


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, help="scene folder, bag, or folder of per-camera images/videos")
    p.add_argument(
        "--intrinsics",
        type=Path,
        required=True,
        help="rig file or folder with every camera's K, distortion, image size",
    )
    p.add_argument("--out", type=Path, required=True, help="rig file to write")
    p.add_argument(
        "--format",
        choices=("yaml", "toml"),
        default=None,
        help="yaml (the nodes' rig) or toml (Pose2Sim Calib.toml); default by --out suffix",
    )
    p.add_argument("--report", type=Path, default=None, help="folder for the report's pictures")
    p.add_argument(
        "--court-points",
        type=Path,
        default=None,
        help="YAML of court landmarks and their pixels (fixes origin, axes, scale)",
    )
    p.add_argument(
        "--person-height", type=float, default=None, help="the people's median stature in m (sets the scale)"
    )
    p.add_argument("--refine-intrinsics", action="store_true", help="also refine focal length and k1")
    p.add_argument("--no-time", action="store_true", help="do not estimate time offsets")
    p.add_argument("--max-offset", type=float, default=0.15, help="largest time offset searched, s")
    p.add_argument(
        "--time-method",
        choices=TIME_METHODS,
        default="gauss_seidel",
        help="time offset estimator: gauss_seidel (one camera at a time, default), "
        "joint (then all offsets refined together; less accurate on the bench so far, "
        "doc/calibration.md) or gauss_seidel_partial (the default before: biased by gaps "
        "in the tracks)",
    )
    p.add_argument(
        "--time-test",
        choices=TIME_TESTS,
        default="kernel",
        help="joint significance test of the offsets: kernel (default: the other cameras' "
        "tracks smoothed as the estimator does) or interpolated (the former: zeroed true "
        "offsets under half a frame)",
    )
    p.add_argument(
        "--backend",
        default=None,
        help="frontend backend for image/video sources (mediapipe (default), synthetic, "
        "sam3d_body); given with a bag, its images are used, not its detections",
    )
    p.add_argument(
        "--frontend-params",
        type=Path,
        default=None,
        help="node params file whose frontend section configures the backend "
        "(default config/<backend>.yaml when shipped, e.g. config/mediapipe.yaml)",
    )
    p.add_argument(
        "--save-detections",
        type=Path,
        default=None,
        metavar="BAG",
        help="also write the detections as a bag of /<cam>/detections (a SOURCE that "
        "skips the backend next time)",
    )
    p.add_argument(
        "--reference",
        type=Path,
        default=None,
        metavar="RIG",
        help="a reference rig of the same cameras (any rig format): print the "
        "calibrated rig's errors against it (tools/rig_compare.py)",
    )
    p.add_argument("--frames", type=int, default=None, help="use at most this many frames")
    p.add_argument("--fps", type=float, default=None, help="frame rate of an image/video source")


def run(args: argparse.Namespace) -> int:
    from maem_ros.core.calibrate.people import calibrate_people
    from maem_ros.core.calibrate.people_data import people_data
    from maem_ros.tools.calibrate.calibrate_report import print_summary, write_report

    try:
        opts = _options(args)
        intr = _intrinsics(args.intrinsics)
        reference = _reference(args.reference)
        frames, fps, images = load_source(args.source, intr, args)
        data = people_data(intr, frames, fps)
    except ValueError as e:  # BadInput and the readers' errors of the user's files
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
        from maem_ros.core.geometry.rig_formats import write_pose2sim_toml

        write_pose2sim_toml(args.out, result.rig.cameras)
    else:
        result.rig.to_yaml(args.out)
    print_summary(result, data, sys.stdout)
    print(f"rig written: {args.out}")
    if reference is not None:
        from maem_ros.tools.calibrate.rig_compare import compare_rigs, format_comparison

        print(format_comparison(compare_rigs(result.rig, reference), str(args.reference)))
    if args.report is not None:
        for path in write_report(result, data, args.report, images):
            print(f"report: {path}")
    return 0


def _options(args):
    from maem_ros.core.calibrate.court import read_court_points
    from maem_ros.core.calibrate.people import PeopleOptions

    if args.person_height is not None and not (0.5 < args.person_height < 2.6):
        raise BadInput(f"--person-height: {args.person_height} m is not a person's stature")
    if args.frames is not None and args.frames < 2:
        raise BadInput(f"--frames: {args.frames}: need at least 2")
    court = read_court_points(args.court_points) if args.court_points is not None else None
    return PeopleOptions(
        refine_intrinsics=args.refine_intrinsics,
        estimate_time=not args.no_time,
        max_offset_s=args.max_offset,
        time_method=args.time_method,
        time_test=args.time_test,
        person_height=args.person_height,
        court=court,
    )


def _reference(path: Path | None) -> Rig | None:
    return None if path is None else _read_rig(path, "--reference", Rig.load)


def _intrinsics(path: Path) -> Rig:
    return _read_rig(path, "--intrinsics", Rig.load_intrinsics)


def _read_rig(path: Path, option: str, read) -> Rig:
    """``read(path)``, any failure as one BadInput line naming ``option`` and the file."""
    if not path.exists():
        raise BadInput(f"{option} {str(path)!r}: no such file or folder")
    try:
        return read(path)
    except (ValueError, OSError, KeyError) as e:
        raise BadInput(f"{option} {str(path)!r}: {' '.join(str(e).split())}") from None
