"""maem-warmup: the CLI compiles every kernel the nodes use into numba's on-disk cache, and a
fresh process then loads all of them without compiling (numba's own counters: signatures
loaded from the cache vs compiled, no timing); the cache lives next to the installed package
(a copied install, as colcon's plain build makes, gets its own); a kernel recompiles when its
own source changes (numba) or a source it imports changes (the warm-up's manifest)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
WARMUP = Path(sys.executable).parent / "maem-warmup"
#: a fresh process: the kernels' own warm-ups (and with "nodes" the nodes' path), then
#: numba's counters of every core kernel as JSON
PROBE = """
import json, sys
from maem_ros.core import kernel_cache as kc
from maem_ros.tools import warmup
before = kc.kernel_counts()
kc.warm_kernels(kc.kernel_modules(sys.argv[2:]))
if sys.argv[1] == "nodes":
    warmup.node_paths()
stats = kc.kernel_stats(before)
print(json.dumps({"file": kc.__file__,
                  "kernels": {s.name: [s.loaded, s.compiled, s.cache_dir] for s in stats}}))
"""
TRIANGULATION = "maem_ros.core.triangulation"
RANSAC = "maem_ros.core.triangulation.ransac_kernel._kernel"


def probe(*args: str, env: dict | None = None, cwd: Path = REPO) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True,
                         timeout=1800, env=env, cwd=cwd)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_warmup(*args: str, env: dict | None = None, cwd: Path = REPO
               ) -> subprocess.CompletedProcess:
    return subprocess.run([str(WARMUP), *args], capture_output=True, text=True, timeout=1800,
                          env=env, cwd=cwd)


@pytest.mark.slow
@pytest.mark.timeout(3600)  # a cold cache compiles every kernel (minutes on a loaded machine)
def test_warmup_leaves_every_node_kernel_cached_for_a_fresh_process() -> None:
    done = run_warmup()
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "signatures compiled" in done.stdout and "node-path frame sets" in done.stdout
    got = probe("nodes")
    kernels = got["kernels"]
    compiled = {k: v for k, v in kernels.items() if v[1]}
    assert not compiled, f"compiled again in a fresh process (not cached): {compiled}"
    loaded = {k for k, v in kernels.items() if v[0]}
    # the gates', clustering's, the pose cost's and RANSAC's kernels all came from the cache
    for name in ("epipolar_kernel.sums_kernel", "reprojection_kernel.reprojection_gate",
                 "clustering_kernel._greedy", "procrustes_kernel._kernel", "ransac_kernel._kernel"):
        assert any(k.endswith(name) for k in loaded), (name, sorted(loaded))
    src = REPO / "maem_ros"
    assert all(Path(v[2]).is_relative_to(src) for v in kernels.values() if v[2]), \
        "an editable install caches next to its source modules"


def copied_install(tmp_path: Path) -> tuple[Path, dict]:
    """The package copied (no caches) into tmp_path/site, as colcon's plain build installs it
    into site-packages, and the environment that imports it from there."""
    site = tmp_path / "site"
    shutil.copytree(REPO / "maem_ros", site / "maem_ros",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("NUMBA_CACHE_DIR", None)
    return site, env


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_copied_install_caches_next_to_itself_and_recompiles_changed_sources(
        tmp_path: Path) -> None:
    site, env = copied_install(tmp_path)
    cache = site / "maem_ros" / "core" / "triangulation" / "__pycache__"
    done = run_warmup("--only", TRIANGULATION, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert str(cache) in done.stdout
    assert list(cache.glob("ransac_kernel.*.nbi")) and list(cache.glob("ransac_kernel.*.nbc"))

    got = probe("kernels", TRIANGULATION, env=env, cwd=tmp_path)
    assert Path(got["file"]).is_relative_to(site)  # the copy imported, not the source tree
    loaded, compiled, where = got["kernels"][RANSAC]
    assert (loaded, compiled) == (1, 0) and Path(where) == cache

    # the kernel's own file changes: numba sees it (content hash) and compiles again
    own = site / "maem_ros" / "core" / "triangulation" / "ransac_kernel.py"
    own.write_text(own.read_text() + "\n# changed\n")
    assert probe("kernels", TRIANGULATION, env=env, cwd=tmp_path)["kernels"][RANSAC][1] == 1
    # now cached again
    assert probe("kernels", TRIANGULATION, env=env, cwd=tmp_path)["kernels"][RANSAC][:2] == [1, 0]

    # a file the kernel imports a constant from changes: numba would keep serving the old
    # kernel; the warm-up finds it stale, deletes it and compiles it again
    dep = site / "maem_ros" / "core" / "geometry" / "multiview.py"
    dep.write_text(dep.read_text() + "\n# changed\n")
    done = run_warmup("--only", TRIANGULATION, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "ransac_kernel.py" in done.stdout and "stale" in done.stdout
    assert "0 signatures compiled" not in done.stdout
    assert probe("kernels", TRIANGULATION, env=env, cwd=tmp_path)["kernels"][RANSAC][:2] == [1, 0]


def test_warmup_rejects_an_unknown_module() -> None:
    done = run_warmup("--only", "maem_ros.core.nowhere")
    assert done.returncode == 2
    assert done.stderr.strip() == ("maem-warmup: --only 'maem_ros.core.nowhere': no module of "
                                   "maem_ros.core or maem_ros.wire starts with it")
