"""maem-warmup: compile every numba kernel the nodes use into numba's on-disk cache, so the
first start of a node after an install loads them (about a second) instead of compiling them
(tens of seconds to minutes).

    maem-warmup            # after pip install / make venv (make does it) / colcon build

numba (``cache=True``) writes each kernel next to its module, in ``__pycache__`` (the source
tree for an editable install, ``install/maem_ros/lib/pythonX/site-packages/...`` for a colcon
install), or in ``NUMBA_CACHE_DIR`` when set (then set it the same way for the nodes). Two
passes:

1. every ``warmup()`` defined by a module of ``maem_ros.core`` or ``maem_ros.wire`` (found by
   walking the packages, so kernels moved between modules stay covered): the kernels with
   their own signatures;
2. the nodes' path on a small simulated frame set, decoded from both detection wires (f32,
   q4) as the association node decodes them, for every shipped params file: association
   (track-assisted, as the node runs it), triangulation. This catches signatures that depend on
   the data's layout (e.g. block ranges of subsampled copies of meshes of several blocks).

Before compiling, cached kernels whose imported sources changed since they were cached are
deleted (numba itself only notices a change of the kernel's own file).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from maem_ros.core import kernel_cache as kc
from maem_ros.core.jit import have_numba

#: shipped params files whose association/triangulation settings the node-path pass runs
SHIPPED_PARAMS = ("demo.yaml", "sportcenter.yaml", "humanm3.yaml", "mediapipe.yaml")
#: simulated frame set of the node-path pass: rig, people seen by all cameras, extras per camera,
#: frames (>= 2: the second frame runs the track-assisted path), mesh vertices (more than two of
#: the epipolar kernel's 4096-point blocks: the block ranges of a subsampled mesh copy then take
#: another array layout) and keypoints
SCENE_RIG, SCENE_PLAYERS, SCENE_EXTRAS, SCENE_FRAMES = "sportcenter6", 4, 1, 2
SCENE_VERTICES, SCENE_KEYPOINTS = 9000, 70
WIRES = ("f32", "q4")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-warmup",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="MODULE",
        help="only the warmup() of modules whose dotted name starts with this "
        "(repeatable; skips the node-path pass), e.g. "
        "maem_ros.core.triangulation",
    )
    p.add_argument("--clean", action="store_true", help="delete the cached kernels first (a full recompile)")
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    return p


def node_paths() -> int:
    """Run the association and triangulation nodes' core path on a simulated frame set,
    decoded from each detection wire, for each shipped params file (pass 2 of the module
    docstring); returns the number of frame sets run. Needs the ROS message wheels (the
    wire codec): without them, raises ImportError."""
    import numpy as np

    from maem_ros.core.association import AssociationParams
    from maem_ros.core.association import warmup as association_warmup
    from maem_ros.core.synthetic import body_template, make_sequence
    from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
    from maem_ros.core.triangulation.ransac import TriangulationParams, triangulate
    from maem_ros.params import load_node_params
    from maem_ros.ros import wire
    from maem_ros.tools.bench.bench_load import load_bench_rig

    rig = load_bench_rig(SCENE_RIG)
    template = body_template(SCENE_VERTICES, SCENE_KEYPOINTS, 0)
    seq = make_sequence(rig, template, np.random.default_rng(0), SCENE_PLAYERS, SCENE_EXTRAS, SCENE_FRAMES)
    sent = {
        layout: [{c: wire.detections_to_msg(fd, layout) for c, fd in fr.frames.items()} for fr in seq]
        for layout in WIRES
    }
    runs = 0
    for name in SHIPPED_PARAMS:
        a = load_node_params(name, "association")
        aparams = AssociationParams.from_mapping(a)
        tparams = TriangulationParams.from_mapping(load_node_params(name, "triangulation"))
        association_warmup(aparams.execution.backend, aparams.epipolar_gate)  # as the node starts
        for layout in WIRES:
            stage = TemporalAssociator(rig, aparams, TemporalParams.from_mapping(a))
            for msgs in sent[layout]:
                frames = {c: wire.msg_to_detections(m, f"/{c}/detections") for c, m in msgs.items()}
                for fd in frames.values():  # as the node prepares each decoded frame
                    stage.gates.prepare(fd)
                res = stage.step(frames, frames[rig.names[0]].stamp_ns)
                triangulate(rig, frames, res.clusters, tparams)
                runs += 1
    return runs


def warm(only: Sequence[str] = (), clean: bool = False, say: Callable[[str], None] = print) -> dict[str, Any]:
    """Passes 1 and 2 (pass 2 without ``only``); returns a summary (kernels loaded, compiled,
    deleted as stale, cache directories, seconds)."""
    t0 = time.monotonic()
    modules = kc.kernel_modules(only)
    found = kc.dispatchers()  # nothing is loaded yet: imports do not call kernels
    stale = list(kc.kernel_files(found)) if clean else kc.stale_kernel_files(found)
    deleted = kc.purge_cache(stale, found) if stale else 0
    for f in stale:
        say(
            f"maem-warmup: deleting the cached kernels of {f.name} ("
            + ("--clean)" if clean else "stale: built from other sources than its imports' current ones)")
        )
    before = kc.kernel_counts()
    kc.warm_kernels(modules)
    node_runs = 0
    if not only:
        try:
            node_runs = node_paths()
        except ImportError as e:  # the ROS message wheels: the nodes cannot run either
            say(f"maem-warmup: node-path pass skipped ({e}); the kernels' own warm-ups ran")
    stats = kc.kernel_stats(before)
    kc.record_sources(kc.dispatchers())
    return {
        "loaded": sum(s.loaded for s in stats),
        "compiled": sum(s.compiled for s in stats),
        "kernels": len(stats),
        "stale_files": [f.name for f in stale],
        "deleted_files": deleted,
        "node_frame_sets": node_runs,
        "cache_dirs": sorted({s.cache_dir for s in stats if s.cache_dir and (s.loaded or s.compiled)}),
        "seconds": time.monotonic() - t0,
        "per_kernel": stats,
    }


def _silent(text: str) -> None:
    """--quiet: the per-kernel lines are not printed."""


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if not have_numba():
        print("maem-warmup: numba is not installed: nothing to compile (the numpy paths run)")
        return 0
    say: Callable[[str], None] = _silent if a.quiet else print
    unknown = [p for p in a.only if not kc.kernel_modules([p])]
    if unknown:
        print(
            f"maem-warmup: --only {unknown[0]!r}: no module of "
            f"{' or '.join(kc.KERNEL_PACKAGES)} starts with it",
            file=sys.stderr,
        )
        return 2
    out = warm(a.only, a.clean, say)
    if not a.quiet:
        for s in out["per_kernel"]:
            if s.compiled:
                say(f"  compiled {s.compiled} signature(s) of {s.name}")
    where = ", ".join(str(Path(d)) for d in out["cache_dirs"]) or "nowhere (no kernel found)"
    print(
        f"maem-warmup: {out['compiled']} signatures compiled, {out['loaded']} loaded from the "
        f"cache, {out['kernels']} kernels, {out['node_frame_sets']} node-path frame sets, "
        f"{out['seconds']:.1f} s; cache: {where}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
