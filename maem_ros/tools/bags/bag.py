"""maem-bag: look into a bag and repair it after a crash.

    maem-bag info BAG                 topics, types, counts, duration; per file complete or cut
    maem-bag recover BAG [--out DIR]  rewrite cut files up to their last whole chunk, rebuild
                                      metadata.yaml; report what was recovered and lost

A bag whose recorder was killed, whose disk filled up or whose copy stopped halfway has a last
file without its summary (and maybe no metadata.yaml). The project's readers read such a bag
as it is (with a warning); ``recover`` makes it a normal bag again for every other tool
(``ros2 bag``, Foxglove, rosbags). Bad input: one line, exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from maem_ros.bagio import BagError, bag_info
from maem_ros.bagio.recover import format_report, recover
from maem_ros.tools.cli import fail


def _duration(info) -> float:
    return (info.end_ns - info.start_ns) / 1e9 if info.message_count else 0.0


def info_lines(bag: str) -> list[str]:
    """What ``maem-bag info`` prints."""
    info = bag_info(bag)
    lines = [
        f"bag:       {bag}",
        f"messages:  {info.message_count:,} (complete ones)",
        f"duration:  {_duration(info):.3f} s (log time {info.start_ns} .. {info.end_ns} ns)",
        "files:",
    ]
    for fs in info.files:
        state = (
            "complete"
            if fs.complete
            else f"CUT SHORT: {fs.problem or 'no summary'}, {fs.size - fs.good_bytes:,} bytes unreadable"
        )
        lines.append(f"  {fs.path.name}: {fs.size / 1e6:.1f} MB, {fs.message_count:,} messages, {state}")
    width = max((len(t) for t in info.topics), default=5)
    lines.append(f"topics ({len(info.topics)}):")
    for topic, msgtype in info.topics.items():
        listed = info.listed.get(topic)
        more = (
            f" (metadata.yaml: {listed:,})"
            if listed is not None and listed != info.counts.get(topic, 0)
            else ""
        )
        lines.append(f"  {topic:<{width}}  {info.counts.get(topic, 0):>7,}  {msgtype}{more}")
    if info.custom:
        lines.append(f"custom data: {', '.join(sorted(info.custom))}")
    if info.damage:
        lines.append(f"warning: {info.damage}")
    return lines


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-bag",
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command", required=True)
    i = sub.add_parser("info", help="topics, counts, duration, files (complete or cut)")
    i.add_argument("bag", help="rosbag2 folder")
    r = sub.add_parser("recover", help="repair a bag after a crash (in place, or into --out)")
    r.add_argument("bag", help="rosbag2 folder")
    r.add_argument(
        "--out",
        metavar="DIR",
        help="write the repaired bag here (must not exist) instead of repairing in place",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "info":
            print("\n".join(info_lines(args.bag)), flush=True)
        else:
            print("\n".join(format_report(recover(args.bag, args.out))), flush=True)
    except BagError as e:
        return fail("maem-bag", e)
    except OSError as e:
        return fail("maem-bag", f"{args.bag}: {e.strerror or e}", 1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
