"""numba's on-disk cache of the kernels (core's, and the wire's q4 decoder), warmed at install
(maem-warmup, doc/cold_start.md).

The kernels are found through each module's own ``warmup()`` (walking the package, so a
kernel that moves between modules stays covered) and counted with numba's own per-dispatcher
counters (signatures loaded from the cache vs compiled). :func:`stale_kernel_files` catches what
numba's cache check misses: numba keys a cached kernel on its own file only, so a kernel that
inlines a helper or reads a constant of another module would keep its old code when only that
module changes. Kept apart from :mod:`maem_ros.core.jit`, which every kernel imports: a change
here does not make the kernels stale.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import os
import pkgutil
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from maem_ros.core.jit import have_numba

#: the packages whose modules are searched for ``warmup()`` functions and numba dispatchers
KERNEL_PACKAGES = ("maem_ros.core", "maem_ros.wire")
#: file (in each cache directory) naming the sources each module's cached kernels were built from
MANIFEST = "maem_kernels.sources.json"


@dataclass
class KernelStats:
    """What a warm-up did for one numba function (a dispatcher): signatures loaded from the
    on-disk cache and signatures compiled (and then written to it)."""

    name: str
    cache_dir: str | None
    loaded: int = 0
    compiled: int = 0


def kernel_modules(prefixes: Sequence[str] = ()) -> list[ModuleType]:
    """Every module of the KERNEL_PACKAGES, imported (in name order); with ``prefixes``, only
    those whose dotted name starts with one of them. An import error propagates: a broken
    kernel module must fail the warm-up, not skip it."""
    names = sorted(
        m.name
        for package in KERNEL_PACKAGES
        for m in pkgutil.walk_packages(importlib.import_module(package).__path__, package + ".")
    )
    names = [n for n in names if not prefixes or any(n.startswith(p) for p in prefixes)]
    return [importlib.import_module(n) for n in names]


def warmup_functions(modules: Sequence[ModuleType]) -> list[Callable[[], None]]:
    """Each module's own module-level ``warmup()`` (defined there, not imported), called with
    its defaults: the kernel registry is the set of these functions."""
    found = []
    for m in modules:
        fn = getattr(m, "warmup", None)
        if callable(fn) and getattr(fn, "__module__", None) == m.__name__:
            found.append(fn)
    return found


def dispatchers(modules: Sequence[ModuleType] | None = None) -> dict[str, Any]:
    """{"module.function": numba dispatcher} of every numba function defined by (or compiled
    from a function of) the imported modules of the KERNEL_PACKAGES (``modules``: only these). Empty
    without numba."""
    if not have_numba():
        return {}
    from numba.core.dispatcher import Dispatcher

    pool = (
        modules
        if modules is not None
        else [
            m
            for n, m in list(sys.modules.items())
            if n.startswith(tuple(p + "." for p in KERNEL_PACKAGES)) and m is not None
        ]
    )
    found: dict[str, Any] = {}
    for m in pool:
        for value in vars(m).values():
            if isinstance(value, Dispatcher):
                f = value.py_func
                found.setdefault(f"{f.__module__}.{f.__qualname__}", value)
    return found


def kernel_counts() -> dict[str, tuple[int, int]]:
    """{dispatcher name: (signatures loaded from the cache, signatures compiled)} so far in
    this process (numba's own counters), over :func:`dispatchers`."""
    return {
        k: (sum(d.stats.cache_hits.values()), sum(d.stats.cache_misses.values()))
        for k, d in dispatchers().items()
    }


def kernel_stats(before: Mapping[str, tuple[int, int]]) -> list[KernelStats]:
    """Per dispatcher, what was loaded and compiled since the :func:`kernel_counts`
    ``before``."""
    out = []
    for name, d in sorted(dispatchers().items()):
        hits, misses = before.get(name, (0, 0))
        s = d.stats
        out.append(
            KernelStats(
                name, s.cache_path, sum(s.cache_hits.values()) - hits, sum(s.cache_misses.values()) - misses
            )
        )
    return out


def warm_kernels(modules: Sequence[ModuleType]) -> list[KernelStats]:
    """Call every ``warmup()`` of ``modules``: each compiles its kernels with the signatures
    the nodes use, or loads them from numba's on-disk cache. Returns :func:`kernel_stats` of
    the calls."""
    before = kernel_counts()
    for fn in warmup_functions(modules):
        fn()
    return kernel_stats(before)


def source_closure(path: Path) -> list[Path]:
    """The maem_ros source files ``path`` imports, directly or through other maem_ros
    modules, ``path`` included (sorted): everything a kernel of that file can inline or
    read a constant from. Found from the import statements (ast), without importing them."""
    import ast

    seen: set[Path] = set()
    todo = [Path(path).resolve()]
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                todo.extend(_imported_files(node, _package_name(f)))
    return sorted(seen)


def _package_name(f: Path) -> str:
    """Dotted name of the package the maem_ros source file f belongs to (relative imports
    start there)."""
    return ".".join(f.relative_to(Path(__file__).resolve().parents[2]).parts[:-1])


def _imported_files(node: Any, package: str) -> list[Path]:
    """Source files of the maem_ros modules an import statement names (for ``from m import
    x``: m, and m.x when x is a submodule)."""
    import ast
    import importlib.util

    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = (
            importlib.util.resolve_name("." * node.level + (node.module or ""), package)
            if node.level
            else node.module or ""
        )
        names = [base] + [f"{base}.{a.name}" for a in node.names]
    else:
        return []
    files = []
    for name in names:
        if name.split(".")[0] != "maem_ros":
            continue
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):  # an attribute, not a submodule
            continue
        if spec is not None and spec.origin and spec.origin.endswith(".py"):
            files.append(Path(spec.origin).resolve())
    return files


def source_digests(path: Path) -> dict[str, str]:
    """{file name relative to the maem_ros package: sha256} of :func:`source_closure`."""
    root = Path(__file__).resolve().parents[1]
    return {
        str(f.relative_to(root)): hashlib.sha256(f.read_bytes()).hexdigest() for f in source_closure(path)
    }


def kernel_files(found: Mapping[str, Any]) -> dict[Path, tuple[str, str]]:
    """{source file: (cache directory, numba's cache file prefix)} of the dispatchers
    ``found`` (:func:`dispatchers`) that cache on disk."""
    out = {}
    for d in found.values():
        cache_dir = d.stats.cache_path
        if cache_dir:
            f = Path(inspect.getfile(d.py_func)).resolve()
            out[f] = (cache_dir, f.stem + ".")
    return out


def _manifest(cache_dir: str) -> dict[str, Any]:
    try:
        return json.loads((Path(cache_dir) / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}


def stale_kernel_files(found: Mapping[str, Any]) -> list[Path]:
    """Kernel source files whose cached kernels may be stale: a file they import (a helper
    they inline, a constant they read) changed since they were cached. numba's cache checks
    only the kernel's own file (a content hash of it) and would keep serving the old code;
    the manifest written by :func:`record_sources` names the whole closure's digests.
    A file with no manifest entry counts as stale only when cache files of it exist."""
    stale = []
    for f, (cache_dir, prefix) in kernel_files(found).items():
        recorded = _manifest(cache_dir).get(f.name)
        cached = any(Path(cache_dir).glob(prefix + "*.nbi"))
        if cached and recorded != source_digests(f):
            stale.append(f)
    return stale


def purge_cache(files: Iterable[Path], found: Mapping[str, Any]) -> int:
    """Delete numba's index and data files of the kernels of ``files`` (from their cache
    directories); the number deleted. numba reads a missing index as an empty cache, so a
    process loading at the same moment compiles instead."""
    where = kernel_files(found)
    removed = 0
    for f in files:
        cache_dir, prefix = where[Path(f).resolve()]
        for p in list(Path(cache_dir).glob(prefix + "*.nbi")) + list(Path(cache_dir).glob(prefix + "*.nbc")):
            p.unlink(missing_ok=True)
            removed += 1
    return removed


def record_sources(found: Mapping[str, Any]) -> None:
    """Write, in each cache directory, the digests of the sources its kernels were compiled
    from (read by :func:`stale_kernel_files`)."""
    by_dir: dict[str, dict[str, Any]] = {}
    for f, (cache_dir, _) in kernel_files(found).items():
        by_dir.setdefault(cache_dir, _manifest(cache_dir))[f.name] = source_digests(f)
    for cache_dir, entries in by_dir.items():
        tmp = Path(cache_dir) / f"{MANIFEST}.{os.getpid()}"
        tmp.write_text(json.dumps(entries, indent=1, sort_keys=True))
        os.replace(tmp, Path(cache_dir) / MANIFEST)
