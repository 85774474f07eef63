"""The parameter tables of README.md and doc/parameters.md are generated from the one parameter
definition (python -m maem_ros.tools.paramdoc) and must be current."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from maem_ros.core.association import AssociationParams
from maem_ros.core.triangulation import TriangulationParams
from maem_ros.tools import paramdoc

REPO = Path(__file__).resolve().parents[1]
DOCS = (REPO / "README.md", REPO / "doc" / "parameters.md")


def _paramdoc(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "maem_ros.tools.paramdoc", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def _table_rows(text: str, name: str) -> list[str]:
    body = text.split(f"<!-- paramdoc:begin {name} -->", 1)[1]
    body = body.split(f"<!-- paramdoc:end {name} -->", 1)[0]
    return [line for line in body.strip().splitlines()[2:]]


@pytest.mark.slow
def test_readme_and_parameter_reference_are_current() -> None:
    """Fails when a parameter, default, bound or description changed and the documents were
    not regenerated (run the command the failure prints)."""
    run = _paramdoc("--check", *map(str, DOCS))
    assert run.returncode == 0, run.stdout + run.stderr


def test_readme_lists_every_method_parameter_with_its_default() -> None:
    rows = _table_rows((REPO / "README.md").read_text(), "method")
    specs = AssociationParams.specs() + TriangulationParams.specs()
    assert [r.split("|")[1].strip().strip("`") for r in rows] == [s.name for s in specs]
    tau_mesh = next(r for r in rows if r.startswith("| `tau_mesh`"))
    assert "`8.0`" in tau_mesh and "> 0" in tau_mesh


#: doc/parameters.md table -> the console script whose --help lists that node's parameters
NODE_SCRIPTS = {"frontend": "maem-frontend", "association": "maem-association",
                "triangulation": "maem-triangulation", "camera": "maem-camera",
                "foxglove": "foxglove"}


def _help_parameter_names(script: str) -> list[str]:
    exe = Path(sys.executable).with_name(script)
    run = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    listed = run.stdout.split("parameters (read-only, set at start):", 1)[1]
    return [line.split()[0] for line in listed.splitlines() if line.startswith("  ")]


@pytest.mark.slow
def test_every_node_table_lists_what_the_node_help_lists() -> None:
    """Each node's table holds exactly the parameters its console script's --help shows, in
    that order; escaped pipes (choices such as 'mean|max' in a description) keep every row at
    five cells."""
    text = (REPO / "doc" / "parameters.md").read_text()
    assert set(NODE_SCRIPTS) == set(paramdoc.NODE_MODULES)
    for node, script in NODE_SCRIPTS.items():
        rows = _table_rows(text, node)
        names = [r.split("|")[1].strip().strip("`") for r in rows]
        assert names == _help_parameter_names(script), node
        for row in rows:
            cells = row.replace("\\|", "").strip("|").split("|")
            assert len(cells) == 5, row


@pytest.mark.slow
def test_check_fails_on_a_stale_table_and_write_repairs_it(tmp_path: Path) -> None:
    readme = (REPO / "README.md").read_text()
    good_row = next(r for r in _table_rows(readme, "method") if r.startswith("| `tau_mesh`"))
    stale = tmp_path / "README.md"
    stale.write_text(readme.replace(good_row, good_row.replace("`8.0`", "`9.0`")))

    run = _paramdoc("--check", str(stale))
    assert run.returncode == 1
    assert "method" in run.stderr and str(stale) in run.stderr

    run = _paramdoc("--write", str(stale))
    assert run.returncode == 0, run.stderr
    assert stale.read_text() == readme
    assert _paramdoc("--check", str(stale)).returncode == 0


def test_bad_documents_are_one_line_and_exit_2(tmp_path: Path) -> None:
    unknown = tmp_path / "unknown.md"
    unknown.write_text("<!-- paramdoc:begin nosuch -->\n<!-- paramdoc:end nosuch -->\n")
    unclosed = tmp_path / "unclosed.md"
    unclosed.write_text("text\n<!-- paramdoc:begin method -->\n| old |\n")
    plain = tmp_path / "plain.md"
    plain.write_text("no tables here\n")
    for path, words in ((unknown, "unknown table 'nosuch'"), (unclosed, "never closed"),
                        (plain, "no paramdoc table markers"),
                        (tmp_path / "missing.md", "cannot read")):
        run = _paramdoc("--check", str(path))
        assert run.returncode == 2, (path, run.stderr)
        assert words in run.stderr and str(path) in run.stderr
        assert len(run.stderr.strip().splitlines()) == 1


def test_regenerate_leaves_text_outside_the_markers_alone() -> None:
    text = ("before\n<!-- paramdoc:begin method -->\nold\n<!-- paramdoc:end method -->\n"
            "after\n")
    new, changed = paramdoc.regenerate(text, "x.md")
    assert changed == ["method"]
    assert new.startswith("before\n<!-- paramdoc:begin method -->\n| parameter |")
    assert new.endswith("<!-- paramdoc:end method -->\nafter\n")
    assert paramdoc.regenerate(new, "x.md") == (new, [])
