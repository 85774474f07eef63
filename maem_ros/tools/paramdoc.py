"""Markdown tables of the parameters, generated from their one definition (core/paramspec.py).

    python -m maem_ros.tools.paramdoc [TABLE ...]                 # print tables (default: all)
    python -m maem_ros.tools.paramdoc --check README.md doc/parameters.md   # exit 1 if stale
    python -m maem_ros.tools.paramdoc --write README.md doc/parameters.md   # regenerate in place

A document holds each generated table between two marker comments::

    <!-- paramdoc:begin TABLE -->
    | parameter | type | default | allowed | meaning |
    ...
    <!-- paramdoc:end TABLE -->

TABLE is ``method`` (the core ``AssociationParams`` and ``TriangulationParams``: the method's
thresholds and variants, which the offline tools read too) or a node's name (``frontend``,
``association``, ``triangulation``, ``camera``, ``foxglove``: every parameter that node
declares, as its ``--help`` lists them). Node tables import the node modules, so they need
rclpy; the ``method`` table does not.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from ..core.paramspec import ParamSpec

#: node table name -> (module, its attributes holding the specs the node declares and its
#: ``--help`` lists, in that order: a ParamSpec or a sequence of them)
NODE_MODULES = {
    "frontend": ("maem_ros.ros.frontend_node", ("PARAMS",)),
    "association": ("maem_ros.ros.association_node", ("PARAMS",)),
    "triangulation": ("maem_ros.ros.triangulation_node", ("PARAMS",)),
    "camera": ("maem_ros.ros.camera_node", ("SOURCE", "PARAMS")),
    "foxglove": ("maem_ros.ros.foxglove_node", ("PARAMS",)),
}

HEADER = "| parameter | type | default | allowed | meaning |\n|---|---|---|---|---|"

_TAG = re.compile(r"<(?=[A-Za-z/])")
_MARKER = re.compile(r"<!-- paramdoc:(begin|end) ([A-Za-z0-9_-]+) -->")


class DocError(Exception):
    """A document that cannot be checked or written: one line naming it."""


def method_specs() -> tuple[ParamSpec, ...]:
    """The method's parameters: association then triangulation (core dataclasses)."""
    from ..core.association import AssociationParams
    from ..core.triangulation import TriangulationParams

    return AssociationParams.specs() + TriangulationParams.specs()


def node_specs(node: str) -> tuple[ParamSpec, ...]:
    """Every parameter the node declares, in its ``--help`` order."""
    module_name, attributes = NODE_MODULES[node]
    module = importlib.import_module(module_name)
    out: list[ParamSpec] = []
    for attribute in attributes:
        value = getattr(module, attribute)
        out.extend([value] if isinstance(value, ParamSpec) else value)
    return tuple(out)


def table_sources() -> dict[str, Callable[[], Sequence[ParamSpec]]]:
    """Table name -> function returning its specs, in document order."""
    out: dict[str, Callable[[], Sequence[ParamSpec]]] = {"method": method_specs}
    for node in NODE_MODULES:
        out[node] = lambda node=node: node_specs(node)  # type: ignore[misc]  # node bound by default
    return out


def _cell(text: str) -> str:
    """Text safe inside a markdown table cell: no line breaks, pipes escaped, and ``<name>``
    escaped so that a renderer does not take it for an HTML tag."""
    return _TAG.sub(r"\\<", " ".join(str(text).split()).replace("|", "\\|"))


def _code_cell(text: str) -> str:
    """Text for a code span inside a table cell: only pipes need escaping there."""
    return " ".join(str(text).split()).replace("|", "\\|")


def format_default(spec: ParamSpec) -> str:
    """The default as a params file writes it: true/false, numbers, strings, [] lists."""
    value = spec.default
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    if isinstance(value, str):
        return value if value else '""'
    return repr(value)


def format_allowed(spec: ParamSpec) -> str:
    """Bounds or choices: ``> 0``, ``>= 0, <= 1``, ``mean, max``; empty when unconstrained."""
    if spec.choices:
        return ", ".join('""' if c == "" else c for c in spec.choices)
    return spec.constraints()


def render_table(specs: Sequence[ParamSpec]) -> str:
    """One markdown table, a row per parameter in declaration order."""
    rows = [HEADER]
    for spec in specs:
        allowed = format_allowed(spec)
        rows.append(
            f"| `{spec.name}` | {spec.ptype.__name__} | `{_code_cell(format_default(spec))}` "
            f"| {_cell(allowed)} | {_cell(spec.description)} |"
        )
    return "\n".join(rows)


def render(name: str) -> str:
    """The table called ``name``; DocError for an unknown name."""
    sources = table_sources()
    if name not in sources:
        raise DocError(f"unknown table {name!r} (known: {', '.join(sources)})")
    return render_table(sources[name]())


def regenerate(text: str, where: str) -> tuple[str, list[str]]:
    """``text`` with every marked table regenerated, and the names of the tables that changed.

    DocError (naming ``where``) for unbalanced, nested or unknown markers."""
    out: list[str] = []
    changed: list[str] = []
    pos = 0
    open_name: str | None = None
    open_end = 0
    for m in _MARKER.finditer(text):
        kind, name = m.group(1), m.group(2)
        line = text.count("\n", 0, m.start()) + 1
        if kind == "begin":
            if open_name is not None:
                raise DocError(f"{where}:{line}: paramdoc:begin {name} inside table {open_name}")
            out.append(text[pos : m.end()])
            open_name, open_end = name, m.end()
            continue
        if open_name != name:
            raise DocError(f"{where}:{line}: paramdoc:end {name} without its begin")
        try:
            table = render(name)
        except DocError as e:
            raise DocError(f"{where}:{line}: {e}") from None
        new = "\n" + table + "\n"
        if text[open_end : m.start()] != new:
            changed.append(name)
        out.append(new + m.group(0))
        pos, open_name = m.end(), None
    if open_name is not None:
        raise DocError(f"{where}: paramdoc:begin {open_name} is never closed")
    out.append(text[pos:])
    return "".join(out), changed


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as e:
        raise DocError(f"{path}: cannot read ({e.strerror or e})") from None


def check_or_write(paths: Sequence[Path], write: bool) -> int:
    """0 when every file is current (or was rewritten), 1 when ``--check`` found a stale table."""
    stale = 0
    for path in paths:
        text = _read(path)
        if not _MARKER.search(text):
            raise DocError(f"{path}: holds no paramdoc table markers")
        new, changed = regenerate(text, str(path))
        if not changed:
            continue
        if write:
            path.write_text(new, encoding="utf-8")
            print(f"{path}: regenerated {', '.join(changed)}")
        else:
            stale += 1
            print(
                f"{path}: parameter table(s) {', '.join(changed)} out of date; run "
                f"python -m maem_ros.tools.paramdoc --write {path}",
                file=sys.stderr,
            )
    return 1 if stale else 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m maem_ros.tools.paramdoc",
        description=__doc__.splitlines()[0],
        epilog=f"tables: {', '.join(['method', *NODE_MODULES])}",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--check", action="store_true", help="FILES: exit 1 when a marked table differs from the definitions"
    )
    mode.add_argument("--write", action="store_true", help="FILES: regenerate marked tables")
    p.add_argument(
        "names",
        nargs="*",
        metavar="TABLE|FILE",
        help="tables to print, or with --check/--write the documents",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.check or args.write:
            if not args.names:
                raise DocError("--check/--write need at least one document")
            return check_or_write([Path(n) for n in args.names], write=args.write)
        for name in args.names or list(table_sources()):
            print(f"<!-- paramdoc:begin {name} -->\n{render(name)}\n<!-- paramdoc:end {name} -->\n")
    except DocError as e:
        print(f"paramdoc: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
