"""ROS params files and shipped config lookup, without rclpy.

A params file has the ROS 2 layout ``node_name: {ros__parameters: {...}}`` with an
optional ``/**`` section shared by every node. Offline tools (maem-eval, maem-bench)
read the same files the nodes use.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import yaml

from maem_ros.core.errors import InputError

_REPO_CONFIG = Path(__file__).resolve().parent.parent / "config"


def config_dirs() -> list[Path]:
    """Where shipped config lives: the source tree, then the install prefix (pip / colcon)."""
    dirs = [_REPO_CONFIG, Path(sys.prefix) / "share" / "maem_ros" / "config"]
    try:  # colcon workspace
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("maem_ros")) / "config")
    except Exception:  # noqa: BLE001 - ament index absent or package not registered
        pass
    return [d for d in dirs if d.is_dir()]


def resolve_config_path(value: str | Path, subdir: str = "") -> Path:
    """An existing path as given, else a shipped config entry by name.

    ``resolve_config_path("sportcenter6", "rigs")`` finds config/rigs/sportcenter6.yaml.
    """
    p = Path(value).expanduser()
    if p.exists():
        return p
    for d in config_dirs():
        for cand in (d / subdir / p, d / subdir / f"{p}.yaml", d / p):
            if cand.exists():
                return cand
    raise InputError(
        f"config {str(value)!r}: not a file/folder and not a shipped "
        f"config{'/' + subdir if subdir else ''} entry",
        "bad_config",
    )


def resolve_rig_path(value: str | Path) -> Path:
    """A rig YAML / camera-JSON folder path, or the name of a shipped rig (config/rigs/)."""
    return resolve_config_path(value, "rigs")


def load_node_params(params_file: str | Path, node_name: str) -> dict[str, Any]:
    """The parameters a node called ``node_name`` gets from a params file (``/**`` merged first)."""
    path = resolve_config_path(params_file)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise InputError(
            f"params file {str(path)!r}: unreadable ({' '.join(str(e).split())})", "bad_config"
        ) from None
    if not isinstance(data, dict):
        raise InputError(f"params file {str(path)!r}: expected a mapping of node names", "bad_config")
    out: dict[str, Any] = {}
    for key in ("/**", node_name, f"/{node_name}", f"/**/{node_name}"):
        section = data.get(key)
        if section is None:
            continue
        # a section without ros__parameters would silently give the node defaults
        if (
            not isinstance(section, dict)
            or "ros__parameters" not in section
            or not isinstance(section["ros__parameters"] or {}, dict)
        ):
            raise ValueError(f"params file {str(path)!r}: section {key!r} needs 'ros__parameters:'")
        out.update(section["ros__parameters"] or {})
    return out
