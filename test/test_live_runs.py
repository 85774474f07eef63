"""maem-bench --live --runs / --stress (tools/bench/live_runs.py): the figures on known latencies,
the CPU hog, the worst of several runs and the command line."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from maem_ros.tools.bench.live_report import Observed, cpu_times, latency_figures, steal_pct
from maem_ros.tools.bench.live_runs import (
    RECOVERED_MS,
    accounting,
    aggregate,
    hog_window,
    start_hog,
    stress_figures,
)

RATE = 10.0  # frames per second of the synthetic latency series


def test_stress_figures_on_a_known_latency_series() -> None:
    """Frames at 10 fps: 20 ms before the hog (2-4 s), 300 ms and every other frame skipped
    during it, then 200 ms for 0.6 s after it and 20 ms again: recovered 0.4 s after its end
    (the first moment from which the next 0.5 s, five frames, have a median under 50 ms:
    200, 200, 20, 20, 20)."""
    lat: list[float | None] = []
    for f in range(80):
        t = f / RATE
        if 2.0 <= t < 4.0:
            lat.append(None if f % 2 else 300.0)
        elif 4.0 <= t < 4.6:
            lat.append(200.0)
        else:
            lat.append(20.0)
    st = stress_figures(lat, RATE, 2.0, 4.0)
    assert st["latency_ms_median_during"] == 300.0 and st["frames_without_poses_during"] == 10
    assert st["recovery_s"] == pytest.approx(0.4)
    assert st["p50_1s_after_ms"] == 20.0 and st["frames_without_poses_after"] == 0
    never = stress_figures([20.0] * 20 + [RECOVERED_MS + 1] * 60, RATE, 2.0, 4.0)
    assert never["recovery_s"] is None  # not back within the run


def test_latency_figures_say_where_each_slow_frame_waited() -> None:
    """Three frames at 10 fps: frame 1 waited 80 ms for the association and its camera 2 was
    30 ms late; frame 2 has no poses (in the first second of the stream; at 2 fps it is not)."""
    stamps = [100, 200, 300]
    run = Observed(stamps=stamps, messages={}, t0=1000.0, wall=1.0, cpu0={}, cpu1={},
                   poses={100: (1000.02, None), 200: (1000.2, None)}, diags={}, hog_at=None,
                   clusters={100: 1000.01, 200: 1000.18},
                   publisher_late_s={"c1": [0.001, 0.002, 0.001], "c2": [0.002, 0.03]})
    fig = latency_figures(run, RATE)
    assert fig["slowest_frames"] == [(1, 100.0, 80.0, 30.0), (0, 20.0, 10.0, 2.0)]
    assert fig["frames_without_poses"] == 1 and fig["latency_ms_by_frame"][2] is None
    assert fig["publisher_late_ms_median"] == 2.0  # every publish of every camera
    assert fig["publisher_late_ms_by_frame"] == [2.0, 30.0, 1.0]  # the latest camera's
    assert fig["frames_without_poses_first_s"] == 1
    assert latency_figures(run, 2.0)["frames_without_poses_first_s"] == 0


def test_steal_share_between_two_readings() -> None:
    assert steal_pct((10, 1000), (60, 2000)) == 5.0
    assert steal_pct(None, (60, 2000)) is None and steal_pct((10, 1000), (10, 1000)) is None
    now = cpu_times()
    if now is not None:  # Linux: steal is part of the total
        assert 0 <= now[0] <= now[1]


def test_accounting_explains_frames_without_poses_by_the_nodes_counts() -> None:
    assoc = {"count/sync_sets": "95", "dropped/behind": "7", "dropped/dds_lost": "30",
             "dropped/association_error": "1"}
    tri = {"frames_dropped": "3", "dropped/behind": "2", "dropped/bad_clusters": "1"}
    acc = accounting(100, 16, 6, assoc, tri)
    assert acc == {"frames_without_poses": 16, "no_set": 5, "no_set_counted": 5,
                   "skipped_association": 7, "skipped_triangulation": 2, "other_drops": 2,
                   "unaccounted": 0}
    assert accounting(100, 20, 6, assoc, tri)["unaccounted"] == 4
    # no /diagnostics from the association: nothing is explained
    assert accounting(100, 100, 6, {}, {})["unaccounted"] == 100


def test_aggregate_reports_the_median_and_the_worst_against_the_targets() -> None:
    runs = [dict(latency_ms_median=20.0, latency_ms_p99=50.0, frames_without_poses_pct=0.0,
                 recall_live=1.0, recall_shortfall=0.0, stress_recovery_s=0.2,
                 load_average_1min=3.0, slowest_frames=[(3, 60.0), (4, 55.0)]),
            dict(latency_ms_median=45.0, latency_ms_p99=90.0, frames_without_poses_pct=0.5,
                 recall_live=0.97, recall_shortfall=0.02, stress_recovery_s=None,
                 load_average_1min=9.0, slowest_frames=[(0, 95.0)]),
            dict(latency_ms_median=25.0, latency_ms_p99=60.0, frames_without_poses_pct=0.2,
                 recall_live=0.99, recall_shortfall=0.0, stress_recovery_s=0.4,
                 load_average_1min=4.0, slowest_frames=[(9, 70.0)])]
    out = aggregate(runs, 60.0)
    assert out["runs"] == 3
    assert "slowest_frames" not in out["worst"]  # where each run's tail was, not a figure to rank
    assert out["median"]["latency_ms_median"] == 25.0 and out["worst"]["latency_ms_p99"] == 90.0
    assert out["worst"]["recall_live"] == 0.97  # lower is worse
    assert out["worst"]["stress_recovery_s"] is None  # a run that never recovered
    assert out["median"]["stress_recovery_s"] == pytest.approx(0.3)
    t = out["targets"]
    assert not t["latency_ms_median"]["met"] and t["latency_ms_p99"]["met"]
    assert t["frames_without_poses_pct"]["met"] and not t["recall_shortfall"]["met"]
    assert not t["stress_recovery_s"]["met"]
    assert set(aggregate(runs, 30.0)["targets"]) == {"latency_ms_p99", "frames_without_poses_pct",
                                                     "stress_recovery_s"}


def test_the_hog_is_centred_and_leaves_time_to_recover() -> None:
    assert hog_window(100.0, 900, 60.0, 5.0) == (105.0, 110.0)  # centred in 15 s
    assert hog_window(100.0, 600, 60.0, 5.0) == (102.0, 107.0)  # 3 s left after it


def test_the_hog_keeps_one_cpu_busy_for_its_time() -> None:
    """The hog process sleeps until its start, then burns CPU for its seconds, then exits."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.time() + 0.3
    proc = start_hog(start, 1.0)
    try:
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert time.time() >= start + 1.0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    assert cpu > 0.1, cpu  # busy (a loaded machine shares the core with it), not asleep


@pytest.mark.parametrize("args,flag", [(["--runs", "0"], "--runs"),
                                        (["--stress", "-1"], "--stress"),
                                        (["--stress", "5", "--frames", "60", "--rate", "30"],
                                         "--stress 5")])
def test_bad_runs_and_stress_arguments_exit_2_with_one_line(args, flag) -> None:
    proc = subprocess.run([sys.executable, "-m", "maem_ros.tools.bench.bench", "--live", *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and flag in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.timeout(600)
def test_bench_live_runs_twice_with_a_hog(scene, tmp_path) -> None:
    """maem-bench --live --runs 2 --stress 1 at 10 fps (the tool and its report, not this
    machine's speed): each run's figures, the median, the worst, the hog's figures, and every
    frame without poses counted by a node."""
    proc = subprocess.run([sys.executable, "-m", "maem_ros.tools.bench.bench", "--live", "--frames",
                           "50", "--vertices", "500", "--wire", "q4", "--rate", "10", "--runs",
                           "2", "--stress", "1", "--json"], capture_output=True, text=True,
                          timeout=580, env=dict(os.environ, TMPDIR=str(tmp_path)))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["runs"] == 2 and len(out["per_run"]) == 2 and out["stress_s"] == 1.0
    for run in out["per_run"]:
        assert run["unaccounted"] == 0, run
        assert 0 <= run["frames_without_poses_first_s"] <= run["frames_without_poses"]
        assert run["latency_ms_p99"] >= run["latency_ms_median"] > 0
        assert "stress_recovery_s" in run
        assert run["association_cpu_ms_per_frame"] > 0 and run["triangulation_cpu_ms_per_frame"] > 0
        assert 0.0 <= run["cpu_steal_pct"] <= 100.0
        assert run["association_new_deferred"] <= run["association_light_steps"] <= run["association_sets"] <= 50
        frame, ms, hop, late = run["slowest_frames"][0]  # where the tail waited
        assert 0 <= frame < 50 and ms == round(run["latency_ms_max"], 1) and hop <= ms and late < ms
    assert out["worst"]["latency_ms_p99"] == max(r["latency_ms_p99"] for r in out["per_run"])
    assert set(out["targets"]) >= {"latency_ms_p99", "frames_without_poses_pct"}
    assert out["settings"]["keep_every_set"] is False
    assert proc.stderr.count("maem-bench --live: run ") == 2
