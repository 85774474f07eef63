"""maem-bench temporal on/off: the load in motion, tracks explaining the known people."""
from __future__ import annotations

import json

import numpy as np
import pytest
from test_bench import _bench

from maem_ros.core.association.pipeline import AssociationParams
from maem_ros.core.synthetic import body_template, make_sequence
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
from maem_ros.sim.rigs import load_rig


@pytest.mark.slow
def test_bench_reports_temporal_on_and_off():
    proc = _bench("--vertices", "300", "--frames", "1", "--repeats", "1",
                  "--straightforward-frames", "0", "--temporal-frames", "6", "--json")
    assert proc.returncode == 0, proc.stderr
    t = json.loads(proc.stdout)["temporal"]
    assert t["frames"] == 6 and t["players"] == 10 and t["detections_per_frame"] == 72
    assert t["on_ms_median"] > 0 and t["off_ms_median"] > 0
    assert t["off_over_on"] == t["off_ms_median"] / t["on_ms_median"]
    # once the tracks run only the 12 people seen by one camera each are left to association
    assert t["detections_left_median"] == 12
    assert t["true_clusters_last_frame"] == 10


def test_the_load_in_motion_moves_the_same_people():
    rig = load_rig("sportcenter6")
    seq = make_sequence(rig, body_template(300, 70, 0), np.random.default_rng(0), 4, 1, 5)
    assert len(seq) == 5 and all(len(fr.truth) == 4 for fr in seq)
    ta = TemporalAssociator(rig, AssociationParams(tau_det=0.5), TemporalParams())
    ids = [ta.step(fr.frames, fr.frames[rig.names[0]].stamp_ns) for fr in seq]
    assert sorted(ids[-1].track_ids.tolist()) == [0, 1, 2, 3]
    assert [r.stats["detections_left"] for r in ids[1:]] == [6] * 4  # the per-camera extras


@pytest.mark.slow
def test_bench_rejects_negative_temporal_frames(capsys):
    proc = _bench("--temporal-frames", "-1")
    assert proc.returncode == 2 and "--temporal-frames" in proc.stderr
