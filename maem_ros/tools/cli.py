"""What the command-line tools share: their one way of refusing bad input (one line
``prog: what is wrong`` on stderr, exit code 2), the ``--params`` / ``--json`` options several
of them take, and printing a report as JSON or YAML."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

#: exit code of a tool given bad input (a missing file, a bad params file, a bad option value)
EXIT_BAD_INPUT = 2


def fail(prog: str, message: object, code: int = EXIT_BAD_INPUT) -> int:
    """Print ``prog: message`` on one line to stderr and return ``code`` (``return fail(...)``
    in a ``main``)."""
    print(f"{prog}: {message}", file=sys.stderr)
    return code


def add_params_argument(p: argparse.ArgumentParser, default: str | None) -> None:
    """``--params``: a params file (the nodes' ROS params YAML), a path or a shipped config name."""
    p.add_argument(
        "--params",
        default=default,
        help="params file: a path or a shipped config name"
        + (f" (default config/{default})" if default else ""),
    )


def check_params_file(path: str) -> None:
    """Read ``path``'s association section: a missing or malformed params file raises
    ValueError (core.errors.InputError) with one line naming it, before a tool starts work."""
    from maem_ros.params import load_node_params

    load_node_params(path, "association")


def add_json_argument(p: argparse.ArgumentParser) -> None:
    """``--json``: print the report as JSON instead of YAML."""
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def print_report(report: dict[str, Any], as_json: bool) -> None:
    """The report on stdout: indented JSON, or YAML in the report's key order."""
    if as_json:
        print(json.dumps(report, indent=2))
    else:
        import yaml

        print(yaml.safe_dump(report, sort_keys=False))
