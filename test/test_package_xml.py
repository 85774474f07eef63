"""package.xml declares every runtime import of maem_ros/ with its rosdep key, so
``rosdep install`` brings what ``ros2 run maem_ros <node>`` needs."""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
#: import name -> rosdep key (rosdistro's rosdep/base.yaml, python.yaml, or ROS packages)
ROSDEP_KEY = {
    "rclpy": "rclpy", "ament_index_python": "ament_index_python",
    "rcl_interfaces": "rcl_interfaces", "builtin_interfaces": "builtin_interfaces",
    "std_msgs": "std_msgs", "sensor_msgs": "sensor_msgs", "geometry_msgs": "geometry_msgs",
    "visualization_msgs": "visualization_msgs", "diagnostic_msgs": "diagnostic_msgs",
    "rosgraph_msgs": "rosgraph_msgs", "tf2_msgs": "tf2_msgs",
    "numpy": "python3-numpy", "scipy": "python3-scipy", "cv2": "python3-opencv",
    "yaml": "python3-yaml", "rosbags": "python3-rosbags-pip", "tqdm": "python3-tqdm",
    "matplotlib": "python3-matplotlib", "numba": "python3-numba",
    "threadpoolctl": "python3-threadpoolctl-pip",
    "foxglove": "python3-foxglove-sdk-pip", "ezc3d": "python3-ezc3d-pip", "mcap": "python3-mcap-pip",
}
#: keys rosdistro lacks, defined in the repository's rosdep.yaml
CUSTOM_KEYS = {"python3-threadpoolctl-pip", "python3-foxglove-sdk-pip", "python3-ezc3d-pip",
               "python3-mcap-pip"}
#: imports of the optional SAM 3D Body backend (frontend/sam3d_body.py): installed with the
#: model's own repository, not by rosdep (doc/sam3d-body.md)
#: mediapipe: the optional mediapipe frontend's wheel (make mediapipe, pip --no-deps); tomli:
#: imported only on Python < 3.11 (ROS 2 Jazzy's Python 3.12 has tomllib)
OPTIONAL = {"torch", "detectron2", "sam_3d_body", "tools", "mediapipe", "tomli"}


def third_party_imports() -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for path in (REPO / "maem_ros").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "maem_ros":
                    out.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return out


@pytest.mark.slow
def test_every_runtime_import_has_an_exec_depend() -> None:
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    exec_deps = {e.text for e in root.iter("exec_depend")}
    imports = third_party_imports()
    unmapped = {m: sorted(f) for m, f in imports.items()
                if m not in ROSDEP_KEY and m not in OPTIONAL}
    assert not unmapped, f"imports without a rosdep key in this test's table: {unmapped}"
    missing = sorted(ROSDEP_KEY[m] for m in imports if m in ROSDEP_KEY
                     and ROSDEP_KEY[m] not in exec_deps)
    assert not missing, f"package.xml lacks <exec_depend> for {missing}"


def test_custom_rosdep_keys_are_defined() -> None:
    defined = yaml.safe_load((REPO / "rosdep.yaml").read_text())
    for key in CUSTOM_KEYS:
        assert defined[key]["ubuntu"]["pip"]["packages"], key
