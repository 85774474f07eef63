"""maem-calibrate: calibrate a camera rig, from the players (``people``) or from a board (``board``).

    maem-calibrate people SOURCE --intrinsics RIG --out RIG.yaml [...]
    maem-calibrate board SOURCE --board charuco:7x5:0.12:0.09:DICT_4X4_50 --out RIG.yaml [...]

``maem-calibrate MODE --help`` lists each mode's options (tools/calibrate_people.py,
tools/calibrate_board.py).
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

#: subcommand -> (module under maem_ros.tools, one-line help)
MODES = {
    "people": ("calibrate_people", "extrinsics, floor, scale and time offsets from the players"),
    "board": ("calibrate_board", "intrinsics and extrinsics from a ChArUco or checkerboard"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="maem-calibrate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="mode", required=True, metavar="MODE")
    for mode, (module, help_text) in MODES.items():
        sp = sub.add_parser(mode, help=help_text, description=help_text)
        sp.set_defaults(module=module)
        try:
            importlib.import_module(f"maem_ros.tools.{module}").add_arguments(sp)
        except ModuleNotFoundError as e:
            if e.name != f"maem_ros.tools.{module}":
                raise
            sp.set_defaults(missing=module)  # this checkout has no such mode yet
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "missing", None):
        print(f"maem-calibrate: mode {args.mode!r} is not available in this installation",
              file=sys.stderr)
        return 2
    return importlib.import_module(f"maem_ros.tools.{args.module}").run(args)


if __name__ == "__main__":
    sys.exit(main())
