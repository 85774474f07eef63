"""maem-bench: a reduced run of the CLI, and the fast vs straightforward association agreeing."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from maem_ros.core.association import PAPER_PIPELINE, AssociationParams, associate
from maem_ros.core.synthetic import body_template, make_frame
from maem_ros.sim.rigs import load_rig
from maem_ros.tools.bench.bench_load import pa_mpjpe_one, straightforward_associate

KEYS = ("cameras", "detections_per_camera", "vertices", "association_ms_median",
        "association_ms_p90", "triangulation_ms_median", "straightforward_association_ms_median",
        "speedup", "association_cpu_ms_median", "association_cpu_ms_min",
        "triangulation_cpu_ms_median", "triangulation_cpu_ms_min")


def _bench(*args: str, timeout: float = 120.0, env: dict | None = None
           ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "maem_ros.tools.bench.bench", *args],
                          capture_output=True, text=True, timeout=timeout, env=env)


@pytest.mark.slow
def test_bench_json_reduced_load():
    proc = _bench("--vertices", "500", "--frames", "1", "--repeats", "1",
                  "--straightforward-frames", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout, parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    for k in KEYS:
        assert k in out, k
    assert (out["cameras"], out["detections_per_camera"], out["vertices"]) == (6, 12, 500)
    assert out["clusters_identical"] is True
    assert out["true_clusters_recovered"] == out["true_clusters"] == 10
    for k in KEYS[3:]:
        assert np.isfinite(out[k]) and out[k] > 0, k
    assert out["speedup"] == pytest.approx(out["straightforward_association_ms_median"]
                                           / out["paper_association_ms_median"])
    assert out["clustering"] == "consistent"
    assert out["association_cpu_ms_min"] <= out["association_cpu_ms_median"]
    assert out["load_average_1min"] >= 0.0
    assert set(out["targets"]) == {"association_ms_median", "speedup", "triangulation_ms_median"}


@pytest.mark.slow
def test_bench_rejects_bad_arguments():
    proc = _bench("--vertices", "0", "--json")
    assert proc.returncode == 2 and "--vertices" in proc.stderr


@pytest.fixture(scope="module")
def load():
    rig = load_rig("sportcenter6")
    rng = np.random.default_rng(1)
    template = body_template(300, 30, seed=1)
    return rig, [make_frame(rig, template, rng, players=6, extras=2) for _ in range(2)]


@pytest.mark.parametrize("options", [
    {}, {"reproj_reduce": "max"}, {"epipolar_distance": "forward"}, {"k_min": 2},
    {"vertex_stride": 4}, {"tau_mesh": 2.0, "k_min": 2}, {"tau_reproj_bbox": 40.0, "k_min": 3},
    {"backend": "numpy"},
])
@pytest.mark.slow
def test_fast_and_straightforward_give_the_same_clusters(load, options):
    """The straightforward reference implements the paper's pipeline."""
    rig, frames = load
    params = AssociationParams.from_mapping({**PAPER_PIPELINE, **options})
    for fr in frames:
        fast = [frozenset(map(tuple, c.members.tolist()))
                for c in associate(rig, fr.frames, params).clusters]
        ref = [frozenset(map(tuple, m.tolist()))
               for m in straightforward_associate(rig, fr.raw, params)]
        assert fast == ref
        if not options:
            assert set(fast) == set(fr.truth)


def test_score_threshold_in_both_paths(load):
    rig, frames = load
    fr = frames[0]
    name = rig.names[2]
    fr.frames[name].scores[:3] = 0.5
    fr.raw[name].scores[:3] = 0.5
    params = AssociationParams.from_mapping(PAPER_PIPELINE)
    fast = associate(rig, fr.frames, params)
    ref = straightforward_associate(rig, fr.raw, params)
    assert [frozenset(map(tuple, c.members.tolist())) for c in fast.clusters] == \
        [frozenset(map(tuple, m.tolist())) for m in ref]
    assert not any((2, d) in map(tuple, c.members.tolist()) for c in fast.clusters
                   for d in range(3))


def test_reference_pa_mpjpe_is_zero_for_a_similarity():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(30, 3))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert pa_mpjpe_one(1.7 * X @ R.T + [1, 2, 3], X) < 1e-12
    assert pa_mpjpe_one(X + rng.normal(0, 0.1, X.shape), X) > 0.01


@pytest.mark.slow
def test_bench_large_load_reduced():
    proc = _bench("--load", "large", "--vertices", "300", "--frames", "1", "--repeats", "1",
                  "--straightforward-frames", "0", "--json", timeout=240)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert (out["load"], out["cameras"], out["detections_per_camera"]) == ("large", 16, 25)
    assert out["true_clusters_recovered"] == out["true_clusters"] == 22
    assert set(out["targets"]) == {"association_ms_median"}
    assert out["targets"]["association_ms_median"]["target"] == 33.0


@pytest.mark.timeout(300)
@pytest.mark.ros
@pytest.mark.slow
def test_bench_live_reduced_run(scene, tmp_path):
    """maem-bench --live: 6 publisher processes through association + triangulation (at 10 fps:
    the test checks the tool and its report, not this machine's speed under CI load). The
    ``scene`` fixture compiles the numba kernels into their on-disk cache first, so on a fresh
    clone the node processes load them instead of each compiling for tens of seconds."""
    proc = _bench("--live", "--frames", "20", "--vertices", "500", "--wire", "q4", "--json",
                  "--rate", "10", timeout=280, env=dict(os.environ, TMPDIR=str(tmp_path)))
    assert proc.returncode == 0, proc.stderr
    assert not list(tmp_path.iterdir())  # its work folder (every camera's messages) is gone
    out = json.loads(proc.stdout)
    assert (out["cameras"], out["frames_published"], out["wire"]) == (6, 20, "q4")
    assert out["frames_without_poses"] <= 4, out
    assert out["latency_ms_median"] > 0 and out["latency_ms_p99"] >= out["latency_ms_median"]
    assert out["recall_offline"] >= 0.8 and out["recall_live"] >= 0.6, out
    assert {"association", "triangulation", "publisher_camera_0"} <= set(out["cpu_percent"])
    # exit code 0, or a teardown stalled in the middleware that the shutdown watchdog ended
    # (named in the report; the stall seen, in rclpy's destroy_node in ~1 run in 35, was a Fast
    # DDS deadlock that ros/fastdds.py now prevents: 0 in 150 runs since)
    assert all(code == 0 or name in out["forced_exits"]
               for name, code in out["exit_codes"].items()), (out["exit_codes"], proc.stderr)
    assert out["dds_profile"].endswith("fastdds.xml")
    assert isinstance(out["partial_sets"], int)


def test_bench_live_rejects_bad_arguments():
    proc = _bench("--live", "--rate", "0")
    assert proc.returncode == 2 and "--rate" in proc.stderr
    proc = _bench("--live", "--bag", "/nonexistent/bag")
    assert proc.returncode == 2 and "--bag" in proc.stderr


@pytest.mark.timeout(120)
@pytest.mark.ros
def test_live_publisher_stops_cleanly_on_sigint(tmp_path):
    """A camera publisher of maem-bench --live that SIGINT reaches while it waits for its
    subscriber ends like a node: between steps, exit code 0, its node torn down."""
    import signal
    import time

    from maem_ros.tools.bench.latency import write_params

    params = write_params("demo.yaml", tmp_path / "params.yaml",
                          frontend={"frames": 2, "num_vertices": 200})
    log = open(tmp_path / "publisher.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "maem_ros.tools.bench.live", "--publish", "camera_0",
                             "--params", str(params), "--work", str(tmp_path),
                             "--messages", str(tmp_path), "--frames", "2",
                             "--rate", "10"], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 90
        while not (tmp_path / "camera_0.pkl").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert (tmp_path / "camera_0.pkl").exists(), (tmp_path / "publisher.log").read_text()
        time.sleep(1.0)  # in its wait for a subscriber (none comes)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, (tmp_path / "publisher.log").read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    text = (tmp_path / "publisher.log").read_text()
    assert text.rstrip().endswith("done") and "published" not in text, text
