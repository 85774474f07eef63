"""maem-export: tracked 3D poses from a bag as TRC, C3D or CSV files for biomechanics tools.

    maem-export BAG --format trc|c3d|csv --out DIR [--topic /maem/poses] [--min-frames N]

Reads the poses layout (doc/design.md §4: ``id``, ``joints`` 3J world metres, NaN = missing) from
``--topic`` (``/maem/poses`` from the triangulation node, or ``/maem/gt_poses`` in bags written
by maem-make-bag), sorted by header stamp.

* The frame rate is 1 / the median header-stamp step. TRC and C3D rows lie on that uniform grid
  from the first stamp; a grid frame without a message (a dropped frame) is a row of missing
  markers, so the time axis stays uniform as OpenSim, Visual3D and Nexus expect.
* ``trc``: one file per track id, ``<bag>_P<id>.trc`` (Pose2Sim / OpenSim layout:
  PathFileType 4 header, DataRate = CameraRate = the frame rate, marker names from the keypoint
  convention, millimetres, missing markers empty). Axes as Pose2Sim writes them for OpenSim
  (Y up: X_trc = y, Y_trc = z, Z_trc = x of the Z-up world); ``--trc-axes zup`` keeps the world.
* ``c3d``: one file ``<bag>.c3d`` with every track (ezc3d): markers ``P<id>_<joint>`` in mm,
  world axes (Z up), residual -1 for a missing marker and 0 otherwise, POINT:RATE = frame rate.
* ``csv``: one file ``<bag>.csv`` in long format, one row per (message, person, joint):
  ``stamp_ns,id,joint,x,y,z`` with the message's header stamp (integer ns), world metres,
  missing coordinates empty. Untracked persons keep id 4294967295 here.

Persons without a confirmed track (id 4294967295) have no identity across frames and are left
out of TRC and C3D (their count is printed). ``--min-frames N`` drops tracks seen in fewer than
N frames (any finite joint) from every format. Bad inputs give one line naming the input, exit 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maem_ros import bagio, wire
from maem_ros.core.skeleton import CONVENTIONS, KeypointConvention, convention_for, get_convention
from maem_ros.tools.cli import fail

#: poses id of a person without a confirmed track
UNTRACKED = wire.UNTRACKED_ID
FORMATS = ("trc", "c3d", "csv")


class InputError(ValueError):
    """A bad input: one line naming it (exit 2)."""


@dataclass
class PoseSeries:
    """Every poses message of a topic, sorted by header stamp.

    stamps (F,) int ns; per frame the ids (P_f,) int64 and joints (P_f,J,3) world m.
    """

    stamps: np.ndarray
    ids: list[np.ndarray]
    joints: list[np.ndarray]
    num_joints: int

    @property
    def num_frames(self) -> int:
        return len(self.stamps)


@dataclass
class Tracks:
    """Tracked persons on the uniform frame grid.

    ids (T,) sorted; joints (K,T,J,3) world m, NaN where a track has no joint or no frame;
    grid (F,) the grid index of every message; rate_hz; t0_ns the first stamp.
    """

    ids: np.ndarray
    joints: np.ndarray
    grid: np.ndarray
    rate_hz: float
    t0_ns: int

    @property
    def num_grid_frames(self) -> int:
        return int(self.joints.shape[0])


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
def read_pose_series(bag: str | Path, topic: str) -> PoseSeries:
    """All poses messages of ``topic`` in ``bag`` (InputError naming the bag/topic/message)."""
    try:
        info = bagio.bag_info(bag)
    except (ValueError, OSError) as e:
        raise InputError(str(e)) from None
    if info.damage:  # cut short by a crash: every complete message is exported
        print(f"maem-export: warning: {info.damage}", file=sys.stderr, flush=True)
    if topic not in info.topics:
        poses = sorted(t for t, ty in info.topics.items() if ty == bagio.POINT_CLOUD2)
        hint = f"; --topic {bagio.GT_TOPIC} exports the ground truth" if bagio.GT_TOPIC in poses else ""
        raise InputError(
            f"bag {str(bag)!r}: no topic {topic!r} (PointCloud2 topics: {', '.join(poses) or 'none'}{hint})"
        )
    if info.topics[topic] != bagio.POINT_CLOUD2:
        raise InputError(
            f"bag {str(bag)!r}: topic {topic!r} is {info.topics[topic]}, expected "
            f"{bagio.POINT_CLOUD2} (poses layout)"
        )
    stamps, ids, joints, j = [], [], [], None
    for m in bagio.read_messages(bag, [topic], info=info):
        try:
            frame = wire.msg_to_poses(m.decode(), topic)
        except (ValueError, KeyError) as e:
            raise InputError(f"bag {str(bag)!r}: {topic} message at log time {m.log_time_ns}: {e}") from None
        if frame.ids.size:
            if j is not None and frame.joints.shape[1] != j:
                raise InputError(
                    f"bag {str(bag)!r}: {topic} at stamp {frame.stamp_ns}: "
                    f"{frame.joints.shape[1]} joints, earlier messages have {j}"
                )
            j = frame.joints.shape[1]
        stamps.append(frame.stamp_ns)
        ids.append(frame.ids)
        joints.append(frame.joints)
    if not stamps:
        raise InputError(f"bag {str(bag)!r}: topic {topic!r} has no messages")
    if j is None:
        raise InputError(f"bag {str(bag)!r}: topic {topic!r} has no person in any message")
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    st = np.asarray(stamps, dtype=np.int64)[order]
    dup = np.flatnonzero(np.diff(st) == 0)
    if dup.size:
        raise InputError(f"bag {str(bag)!r}: {topic}: header stamp {int(st[dup[0]])} appears in two messages")
    return PoseSeries(
        st, [ids[i] for i in order], [joints[i] if joints[i].size else np.zeros((0, j, 3)) for i in order], j
    )


def frame_rate(stamps: np.ndarray, where: str) -> float:
    """Hz from the median stamp step of sorted unique ns ``stamps`` (InputError below 2)."""
    if len(stamps) < 2:
        raise InputError(f"{where}: {len(stamps)} message(s); a frame rate needs at least 2 stamps")
    return 1e9 / float(np.median(np.diff(stamps)))


def grid_tracks(series: PoseSeries, min_frames: int, where: str) -> tuple[Tracks, int, list[int]]:
    """Tracked persons on the uniform grid; also (untracked person-frames, ids dropped by
    ``min_frames``). InputError when two messages fall on one grid frame (irregular stamps)."""
    rate = frame_rate(series.stamps, where)
    step_ns = 1e9 / rate
    grid = np.rint((series.stamps - series.stamps[0]) / step_ns).astype(np.int64)
    clash = np.flatnonzero(np.diff(grid) == 0)
    if clash.size:
        a, b = series.stamps[clash[0]], series.stamps[clash[0] + 1]
        raise InputError(
            f"{where}: stamps {int(a)} and {int(b)} fall on one frame of the "
            f"{rate:.3f} Hz grid (irregular stamps)"
        )
    all_ids = np.concatenate(series.ids)
    untracked = int(np.sum(all_ids == UNTRACKED))
    tracked = np.unique(all_ids[all_ids != UNTRACKED])
    k, t, j = int(grid[-1]) + 1, len(tracked), series.num_joints
    joints = np.full((k, t, j, 3), np.nan)
    seen = np.zeros(t, dtype=np.int64)
    for g, stamp, ids, pj in zip(grid, series.stamps, series.ids, series.joints):
        keep = ids != UNTRACKED
        ordered = np.sort(ids[keep])
        twice = ordered[1:][np.diff(ordered) == 0]
        if twice.size:
            raise InputError(f"{where}: track id {int(twice[0])} appears twice at stamp {int(stamp)}")
        col = np.searchsorted(tracked, ids[keep])
        joints[g, col] = pj[keep]
        seen[col] += np.isfinite(pj[keep]).all(axis=2).any(axis=1)
    enough = seen >= min_frames
    dropped = [int(i) for i in tracked[~enough]]
    return Tracks(tracked[enough], joints[:, enough], grid, rate, int(series.stamps[0])), untracked, dropped


# ---------------------------------------------------------------------------------------------
# writers
# ---------------------------------------------------------------------------------------------
def _fmt_cells(values: np.ndarray, digits: int) -> np.ndarray:
    """Strings of ``values`` with ``digits`` decimals, '' for NaN (vectorised)."""
    out = np.char.mod(f"%.{digits}f", np.nan_to_num(values))
    return np.where(np.isnan(values), "", out)


def zup_to_yup(xyz: np.ndarray) -> np.ndarray:
    """(...,3) Z-up world -> Pose2Sim's Y-up TRC axes (X_trc = y, Y_trc = z, Z_trc = x)."""
    return xyz[..., [1, 2, 0]]


def write_trc(
    path: Path, joints_m: np.ndarray, names: Sequence[str], rate_hz: float, axes: str = "yup"
) -> None:
    """One track as a TRC file: joints (K,J,3) world metres on the uniform grid, NaN = missing.

    Pose2Sim / OpenSim layout (tab separated): PathFileType 4 header, rate line, marker names
    with X/Y/Z sub-headers, a blank line, then ``Frame# Time X1 Y1 Z1 ...`` (Frame# from 1,
    Time = (Frame# - 1) / rate s), millimetres with 3 decimals, missing markers empty, each row
    ending with a tab (as OpenSim's TRCFileAdapter needs to read empty last markers).
    """
    xyz = zup_to_yup(joints_m) if axes == "yup" else joints_m
    k, j = xyz.shape[:2]
    rate = f"{rate_hz:.6g}"
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{k}\t{j}\tmm\t{rate}\t1\t{k}",
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, j + 1)),
        "",
    ]
    frames = np.arange(1, k + 1)
    cells = np.column_stack(
        [
            frames.astype(str),
            np.char.mod("%.6f", (frames - 1) / rate_hz),
            _fmt_cells(xyz.reshape(k, 3 * j) * 1000.0, 3),
        ]
    )
    # every row ends with a tab: OpenSim's TRC reader drops trailing empty cells otherwise
    rows = ["\t".join(r) + "\t" for r in cells]
    path.write_text("\n".join(header + rows) + "\n")


def write_c3d(path: Path, tracks: Tracks, names: Sequence[str]) -> None:
    """Every track in one C3D (ezc3d): markers P<id>_<joint> in mm, world axes, residual -1 for
    missing markers (0 otherwise), POINT:RATE = the grid rate, frames = the uniform grid."""
    import ezc3d

    k, t, j = tracks.joints.shape[:3]
    labels = tuple(f"P{int(i)}_{n}" for i in tracks.ids for n in names)
    xyz_mm = tracks.joints.reshape(k, t * j, 3).transpose(2, 1, 0) * 1000.0  # (3, M, K)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([tracks.rate_hz])
    c3d["parameters"]["POINT"]["LABELS"]["value"] = labels
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d["data"]["points"] = np.concatenate([xyz_mm, np.ones((1, t * j, k))], axis=0)
    missing = np.isnan(xyz_mm).any(axis=0)
    c3d["data"]["meta_points"] = {
        "residuals": np.where(missing, -1.0, 0.0)[None],
        "camera_masks": np.zeros((7, t * j, k), dtype=bool),
    }
    c3d.write(str(path))


def write_csv(path: Path, series: PoseSeries, keep_ids: set[int], names: Sequence[str]) -> int:
    """Long format ``stamp_ns,id,joint,x,y,z`` (world m, 6 decimals, missing empty) for the
    persons whose id is in ``keep_ids`` or untracked; returns the number of rows."""
    j = series.num_joints
    blocks = []
    for stamp, ids, pj in zip(series.stamps, series.ids, series.joints):
        keep = np.isin(ids, list(keep_ids)) | (ids == UNTRACKED)
        p = int(keep.sum())
        if not p:
            continue
        cells = np.column_stack(
            [
                np.full(p * j, str(int(stamp))),
                np.repeat(ids[keep].astype(str), j),
                np.tile(np.asarray(names), p),
                _fmt_cells(pj[keep].reshape(p * j, 3), 6),
            ]
        )
        blocks.append("\n".join(",".join(r) for r in cells))
    path.write_text("stamp_ns,id,joint,x,y,z\n" + "".join(b + "\n" for b in blocks))
    return sum(b.count("\n") + 1 for b in blocks)


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-export",
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bag", help="rosbag2 folder (metadata.yaml + .mcap)")
    p.add_argument("--format", required=True, choices=FORMATS, help="output format")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--topic", default="/maem/poses", help="poses topic (default /maem/poses)")
    p.add_argument("--min-frames", type=int, default=1, help="drop tracks seen in fewer frames (default 1)")
    p.add_argument(
        "--convention",
        choices=sorted(CONVENTIONS),
        help="keypoint convention of the joints (default: the one with J joints)",
    )
    p.add_argument(
        "--trc-axes",
        choices=("yup", "zup"),
        default="yup",
        help="TRC axes: yup = Pose2Sim/OpenSim (default), zup = world axes",
    )
    return p


def _convention(name: str | None, num_joints: int, where: str) -> KeypointConvention:
    try:
        conv = get_convention(name) if name else convention_for(num_joints)
    except ValueError as e:
        raise InputError(f"{where}: {e}") from None
    if conv.num_joints != num_joints:
        raise InputError(f"{where}: {num_joints} joints, convention {conv.name} has {conv.num_joints}")
    return conv


def _out_dir(out: str) -> Path:
    path = Path(out)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"--out {out!r}: cannot create the folder ({e.strerror})") from None
    return path


def export(args: argparse.Namespace, log=print) -> list[Path]:
    """Run one export; returns the files written (InputError on bad inputs)."""
    if args.min_frames < 1:
        raise InputError(f"--min-frames: {args.min_frames} must be >= 1")
    where = f"bag {str(args.bag)!r}: {args.topic}"
    series = read_pose_series(args.bag, args.topic)
    conv = _convention(args.convention, series.num_joints, where)
    tracks, untracked, dropped = grid_tracks(series, args.min_frames, where)
    out = _out_dir(args.out)
    stem = Path(args.bag).resolve().name
    log(
        f"{where}: {series.num_frames} messages, {tracks.rate_hz:.3f} Hz, "
        f"{len(tracks.ids)} tracks ({conv.name}, {conv.num_joints} joints)"
    )
    if dropped:
        log(
            f"skipped {len(dropped)} track(s) seen in fewer than {args.min_frames} frames: "
            f"{', '.join(map(str, dropped))}"
        )
    if untracked and args.format != "csv":
        log(f"left out {untracked} untracked person-frame(s) (id {UNTRACKED}, no identity)")
    if args.format != "csv" and not len(tracks.ids):
        raise InputError(f"{where}: no tracked person to export")
    written: list[Path] = []
    if args.format == "trc":
        for col, tid in enumerate(tracks.ids):
            path = out / f"{stem}_P{int(tid)}.trc"
            write_trc(path, tracks.joints[:, col], conv.names, tracks.rate_hz, args.trc_axes)
            written.append(path)
    elif args.format == "c3d":
        path = out / f"{stem}.c3d"
        write_c3d(path, tracks, conv.names)
        written.append(path)
    else:
        path = out / f"{stem}.csv"
        rows = write_csv(path, series, set(int(i) for i in tracks.ids), conv.names)
        log(f"{rows} rows")
        written.append(path)
    for path in written:
        log(f"wrote {path}")
    return written


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        export(args)
    except InputError as e:
        return fail("maem-export", e)
    return 0


if __name__ == "__main__":
    sys.exit(main())
