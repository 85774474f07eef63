"""colcon, as a ROS 2 user builds the package: a fresh workspace with the PyPI ROS wheels and
colcon-common-extensions, ``colcon build`` plain and with ``--symlink-install``, the install
layout, and the installed association node started the way ``ros2 run`` resolves it."""
from __future__ import annotations

import configparser
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers_ros import OutputWatcher, killed_on_exit

# builds the package with colcon and runs its nodes with ros2 run
pytestmark = [pytest.mark.colcon, pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
#: what the package build needs from the source tree (no .venv, bags, tests)
SOURCES = ("setup.py", "setup.cfg", "package.xml", "README.md", "resource", "config", "maem_ros")
COLCON = Path(sys.executable).parent / "colcon"


def console_scripts() -> list[str]:
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    lines = cfg["options.entry_points"]["console_scripts"].strip().splitlines()
    return [line.split("=")[0].strip() for line in lines if line.strip()]


def workspace(tmp_path: Path) -> Path:
    """A fresh colcon workspace with a copy of this package in src/maem_ros."""
    ws = tmp_path / "ws"
    src = ws / "src" / "maem_ros"
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc")
    for name in SOURCES:
        p = REPO / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=ignore)
        else:
            shutil.copy2(p, src / name)
    return ws


def sourced_env(ws: Path) -> dict[str, str]:
    """The environment after ``. install/local_setup.bash`` (what a user's shell has)."""
    out = subprocess.run(["bash", "-c", ". install/local_setup.bash && env -0"], cwd=ws,
                         capture_output=True, check=True, timeout=60,
                         env={**os.environ, "PATH": f"{COLCON.parent}:{os.environ['PATH']}"})
    return dict(item.split("=", 1) for item in out.stdout.decode().split("\0") if "=" in item)


def ros2_run_resolution(env: dict[str, str], package: str, executable: str,
                        share_file: str) -> tuple[Path, Path]:
    """(executable, share file) the way ``ros2 run`` / ``ros2 pkg prefix`` find them: the
    package's prefix from the ament index on AMENT_PREFIX_PATH, then lib/<package>/<exe>."""
    code = ("import sys\nfrom ament_index_python.packages import get_package_prefix, "
            "get_package_share_directory\n"
            f"print(get_package_prefix({package!r}))\n"
            f"print(get_package_share_directory({package!r}))\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True, timeout=60, cwd=env["PWD"]).stdout.split()  # not the repo
    return Path(out[0]) / "lib" / package / executable, Path(out[1]) / share_file


@pytest.mark.parametrize("symlink", [False, True], ids=["plain", "symlink-install"])
def test_colcon_build_install_layout_and_ros2_run(tmp_path: Path, symlink: bool) -> None:
    assert COLCON.is_file(), "colcon missing: it comes with the test extra (pip install -e .[test])"
    ws = workspace(tmp_path)
    cmd = [str(COLCON), "build", "--event-handlers", "console_direct-"] + (
        ["--symlink-install"] if symlink else [])
    build = subprocess.run(cmd, cwd=ws, capture_output=True, text=True, timeout=600,
                           env={**os.environ, "PATH": f"{COLCON.parent}:{os.environ['PATH']}"})
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]

    prefix = ws / "install" / "maem_ros"
    missing = [s for s in console_scripts() if not (prefix / "lib" / "maem_ros" / s).is_file()]
    assert not missing, f"not installed in lib/maem_ros: {missing}"
    shipped = sorted(p.name for p in (REPO / "config").glob("*.yaml"))
    assert shipped and sorted(
        p.name for p in (prefix / "share" / "maem_ros" / "config").glob("*.yaml")) == shipped
    assert sorted(p.name for p in (prefix / "share/maem_ros/config/rigs").glob("*.yaml")) == \
        sorted(p.name for p in (REPO / "config" / "rigs").glob("*.yaml"))
    assert (prefix / "share/ament_index/resource_index/packages/maem_ros").is_file()
    assert (prefix / "share/maem_ros/package.xml").is_file()

    env = sourced_env(ws)
    exe, params = ros2_run_resolution(env, "maem_ros", "association", "config/demo.yaml")
    assert exe.is_file() and params.is_file() and str(params).startswith(str(ws))
    # the installed copy is what imports (not the source tree's editable install) and it finds
    # its shipped config through the ament index
    code = ("import maem_ros.params as p; print(p.__file__); "
            "print(p.resolve_config_path('demo.yaml')); print(p.resolve_rig_path('sportcenter6'))")
    where = subprocess.run([sys.executable, "-c", code], cwd=ws, env=env, capture_output=True,
                           text=True, timeout=60)
    assert where.returncode == 0, where.stderr
    assert all(line.startswith(str(ws)) for line in where.stdout.split()), where.stdout

    proc = subprocess.Popen([str(exe), "--ros-args", "--params-file", str(params)], env=env,
                            cwd=ws, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with killed_on_exit(proc):
        out = OutputWatcher(proc)
        # the node logs its subscriptions once it is up
        assert out.wait_line("-> /maem/clusters", 120) and proc.poll() is None, out.text()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 0, out.text()
