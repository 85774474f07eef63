"""The batched track stage (core/tracking/temporal.py) makes exactly the decisions of its straightforward
per-camera implementation (test/temporal_reference.py): every frame's clusters, members, costs,
track ids, flags and statistics, and the tracks' states, on the bench load in motion (several
seeds, people walking through each other) and on constructed crossing / occlusion sequences."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from maem_ros.core.association.pipeline import AssociationParams
from maem_ros.core.synthetic import body_template, make_sequence
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
from maem_ros.tools.bench.bench_load import load_bench_rig

from helpers_scene import Person, ring_rig, walk_frame
from temporal_reference import ReferenceTemporalAssociator
from test_temporal import PARAMS


def assert_same_step(a, b, f: int) -> None:
    """Two TemporalResults of frame f are identical (timings apart)."""
    assert len(a.clusters) == len(b.clusters), f"frame {f}: cluster count"
    for ca, cb in zip(a.clusters, b.clusters):
        np.testing.assert_array_equal(ca.members, cb.members, err_msg=f"frame {f}")
        np.testing.assert_array_equal(ca.costs, cb.costs, err_msg=f"frame {f}")
    np.testing.assert_array_equal(a.track_ids, b.track_ids, err_msg=f"frame {f}")
    np.testing.assert_array_equal(a.flags, b.flags, err_msg=f"frame {f}")
    stats = lambda r: {k: v for k, v in r.stats.items() if not k.startswith("t_")}
    assert stats(a) == stats(b), f"frame {f}"


def assert_same_tracks(fast, ref, f: int) -> None:
    assert [(t.key, t.id, t.hits, t.misses) for t in fast.tracker.tracks] == \
        [(t.key, t.id, t.hits, t.misses) for t in ref.tracker.tracks], f"frame {f}"
    for t, r in zip(fast.tracker.tracks, ref.tracker.tracks):
        np.testing.assert_array_equal(t.x, r.x, err_msg=f"frame {f}")
        np.testing.assert_array_equal(t.offsets, r.offsets, err_msg=f"frame {f}")


def run_both(rig, seq, params: AssociationParams, temporal: TemporalParams) -> int:
    """Step both implementations over seq (frames dicts); returns the frames with tracks."""
    fast = TemporalAssociator(rig, params, temporal)
    ref = ReferenceTemporalAssociator(rig, params, temporal)
    tracked = 0
    for f, frames in enumerate(seq):
        stamp = next(iter(frames.values())).stamp_ns
        a, b = fast.step(frames, stamp), ref.step(frames, stamp)
        assert_same_step(a, b, f)
        assert_same_tracks(fast, ref, f)
        tracked += a.stats["detections_explained"] > 0
    return tracked


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("verify", ["sparse", "mesh"])
@pytest.mark.slow
def test_batched_stage_equals_the_reference_on_the_bench_load_in_motion(seed, verify):
    rig = load_bench_rig("sportcenter6")
    template = body_template(400, 70, seed)
    seq = make_sequence(rig, template, np.random.default_rng(seed), players=8, extras=2,
                        frames=14, px_noise=1.5, speed=3.0)
    tracked = run_both(rig, [fr.frames for fr in seq], AssociationParams(),
                       TemporalParams(verify_epipolar=verify))
    assert tracked >= 10  # the track stage ran on nearly every frame


def test_new_people_are_associated_alike_whatever_scored_below_tau_det():
    """A third of the detections scored under tau_det: step 5 (which copies only the leftovers
    that scored tau_det or more) makes the reference's decisions and statistics, whose step 5
    is given every leftover."""
    rig = load_bench_rig("sportcenter6")
    seq = make_sequence(rig, body_template(400, 70, 3), np.random.default_rng(3), players=8, extras=2,
                        frames=10, px_noise=1.5, speed=3.0)
    rng = np.random.default_rng(4)
    low = [{c: dataclasses.replace(fd, scores=np.where(rng.random(fd.n) < 1 / 3, 0.5, fd.scores))
            for c, fd in fr.frames.items()} for fr in seq]
    params = AssociationParams()
    assert sum(int((fd.scores < params.tau_det).sum()) for fr in low for fd in fr.values()) > 50
    assert run_both(rig, low, params, TemporalParams()) >= 7


@pytest.mark.parametrize("temporal", [TemporalParams(), TemporalParams(refine_px=0.0),
                                      TemporalParams(pose_weight=0.0, verify_epipolar="none")])
def test_batched_stage_equals_the_reference_on_crossing_and_occlusion(temporal):
    """Two people walking through each other, a third hidden from every camera for frames
    8..12 and from two cameras later (few views, one view)."""
    rig = ring_rig(4)
    people = [Person((-3, 0.25), 6, v=(3.0, 0.0)), Person((3, -0.25), 7, v=(-3.0, 0.0)),
              Person((0, -3), 8, v=(0.2, 1.5))]
    cams = rig.names

    def seen(cam, k, f):
        if k != 2:
            return True
        if f in range(8, 13):
            return False
        return not (f >= 20 and cam in cams[:2 + (f >= 26)])

    seq = [walk_frame(rig, people, f, seen=lambda cam, k, f=f: seen(cam, k, f))[0]
           for f in range(34)]
    assert run_both(rig, seq, PARAMS, temporal) >= 30


def test_batched_stage_equals_the_reference_when_the_pair_gates_reject_members():
    """A detection carrying another person's 3D pose fails the PA-MPJPE gate in verification."""
    rig = ring_rig(5)
    people = [Person((-2, 0), 1, v=(1.0, 0.0)), Person((2, 0.5), 2, v=(-1.0, 0.0))]
    wrong = lambda cam, k: 1 - k if (cam == rig.names[3] and k == 0) else k
    seq = [walk_frame(rig, people, f, kpts3d_of=wrong)[0] for f in range(12)]
    run_both(rig, seq, dataclasses.replace(PARAMS, tau_cost=0.05), TemporalParams())


def test_batched_stage_equals_the_reference_on_contested_candidates():
    """Two people overlapping in two of four views, each track's pose swapped for the other's
    at frame 4 (test_temporal: the contested candidates ordered by the tracks' other views)."""
    rig = ring_rig(4, height=0.9, phase=0.0, target=(0.0, 0.0, 0.9))
    a, b = Person((0.7, 0.0), 31), Person((-0.7, 0.0), 31)
    b.joints = a.joints + np.random.default_rng(31).normal(0.0, 0.08, a.joints.shape)
    params = AssociationParams(k_min=2)
    fast = TemporalAssociator(rig, params, TemporalParams())
    ref = ReferenceTemporalAssociator(rig, params, TemporalParams())
    for f in range(8):
        if f == 4:
            for ta in (fast, ref):
                t0, t1 = ta.tracker.tracks
                t0.offsets, t1.offsets = t1.offsets.copy(), t0.offsets.copy()
        frames = walk_frame(rig, [a, b], f)[0]
        stamp = frames["cam0"].stamp_ns
        assert_same_step(fast.step(frames, stamp), ref.step(frames, stamp), f)
        assert_same_tracks(fast, ref, f)
