"""``maem-calibrate``: calibrate a rig. Subcommands: ``people`` (from the players,
tools/calibrate/calibrate_people.py) and ``board`` (from a ChArUco or checkerboard,
tools/calibrate/calibrate_board.py). How-to: doc/calibration.md."""

from __future__ import annotations

import argparse
import importlib
import importlib.util

SUBCOMMANDS = {
    "people": "maem_ros.tools.calibrate.calibrate_people",
    "board": "maem_ros.tools.calibrate.calibrate_board",
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="maem-calibrate",
        description="calibrate a rig: people "
        "(from the players) or board (ChArUco, checkerboard); how-to: "
        "doc/calibration.md",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    for name, module in SUBCOMMANDS.items():
        if importlib.util.find_spec(module) is None:
            continue  # a subcommand whose module this checkout does not have
        mod = importlib.import_module(module)
        p = sub.add_parser(name, help=(mod.__doc__ or "").split("\n")[0])
        mod.add_arguments(p)
        p.set_defaults(run=mod.run)
    args = ap.parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    raise SystemExit(main())
