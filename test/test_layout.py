"""Architecture rules (doc/design.md §2): core/ never imports rclpy or message packages, ros/
imports neither tools/ nor sim/, bags, capture and the wire codec are ROS-free packages of their own."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "maem_ros"
ROS_MODULES = ("rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "visualization_msgs",
               "diagnostic_msgs", "builtin_interfaces", "rcl_interfaces", "rosgraph_msgs",
               "tf2_msgs")


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module imported anywhere in ``path`` (relative ones resolved)."""
    package = ".".join(path.relative_to(PKG.parent).with_suffix("").parts[:-1])
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def _files(sub: str) -> list[Path]:
    return sorted((PKG / sub).rglob("*.py")) if (PKG / sub).is_dir() else [PKG / f"{sub}.py"]


@pytest.mark.parametrize("sub,forbidden", [
    ("core", ROS_MODULES + ("maem_ros.ros", "maem_ros.tools", "maem_ros.sim", "maem_ros.bagio")),
    ("ros", ("maem_ros.tools", "maem_ros.sim")),
    ("viz", ROS_MODULES + ("maem_ros.ros", "maem_ros.tools", "maem_ros.sim")),
    # bagio serialises rclpy messages it is given with rclpy.serialization, nothing else of ROS
    ("bagio", ("maem_ros.tools", "maem_ros.sim") + ROS_MODULES[1:]),
    ("capture", ROS_MODULES + ("maem_ros.ros", "maem_ros.tools")),
    # the wire codec: offline tools decode bags with it on machines without the ROS wheels
    ("wire", ROS_MODULES + ("maem_ros.ros", "maem_ros.tools", "maem_ros.sim")),
])
def test_layer_does_not_import(sub: str, forbidden: tuple[str, ...]) -> None:
    bad = {f"{p.relative_to(PKG)}: {m}" for p in _files(sub) for m in imported_modules(p)
           if any(m == f or m.startswith(f + ".") for f in forbidden)}
    assert not bad, sorted(bad)


def test_tools_find_the_checkout_files() -> None:
    """Tools that read files of the source checkout (the demo bag, the court points) find them
    from their own location, at the depth of their tools/ subpackage."""
    from maem_ros.tools.bags import record_faults
    from maem_ros.tools.calibrate import calib_bench
    from maem_ros.tools.demo import demo_bag

    repo = PKG.parent
    assert demo_bag.REPO_ROOT == repo
    assert demo_bag.default_bag() == record_faults._default_bag() == repo / "bags" / "demo"
    assert calib_bench.COURT_FILE == repo / "config" / "court_points_fiba.yaml"
    assert calib_bench.COURT_FILE.is_file()
