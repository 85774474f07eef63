"""The track stage's per-frame pair decisions (core/tracking/pair_costs.py): one computation
per distinct pair, the same answers however the pairs are batched, and the semantics of ok and
the capped cost on exact detections of walking people."""

from __future__ import annotations

import numpy as np

from maem_ros.core.association.pipeline import AssociationParams
from maem_ros.core.association.gates import PairGates
from maem_ros.core.tracking.pair_costs import FramePairCosts, same_track_pairs

from helpers_scene import Person, ring_rig, walk_frame

PARAMS = AssociationParams(k_min=3)


def frame_costs(kpts3d_of=None):
    """FramePairCosts of frame 3 of two people walking past four cameras, and the person of
    every detection row per camera index."""
    rig = ring_rig(4)
    people = [Person((-3, -1), 17, v=(1.0, 0.0)), Person((3, 2), 18, v=(-1.0, 0.0))]
    fr, who = walk_frame(rig, people, 3, kpts3d_of=kpts3d_of)
    gates = PairGates(rig, PARAMS)
    by_cam = {rig.index(n): gates.prepare(fd) for n, fd in fr.items()}
    n = max(fd.n for fd in by_cam.values())
    costs = FramePairCosts(gates.frame_set(by_cam), by_cam, PARAMS, PARAMS.epipolar_gate, len(rig), n)
    return costs, {rig.index(c): w for c, w in who.items()}


def all_pairs(who):
    rows = [(ca, da, cb, db) for ca in who for cb in who if ca < cb
            for da in range(len(who[ca])) for db in range(len(who[cb]))]
    ca, da, cb, db = (np.array(x) for x in zip(*rows))
    same = np.array([who[a][i] == who[b][j] for a, i, b, j in rows])
    return ca, cb, da, db, same


def test_same_person_pairs_pass_and_other_pairs_cost_the_cap():
    costs, who = frame_costs()
    ca, cb, da, db, same = all_pairs(who)
    ok, cost = costs.get(ca, cb, da, db)
    assert np.array_equal(ok, same)
    assert np.all(cost[same] < 0.02)  # exact poses: PA-MPJPE 0, epipolar ~0
    assert np.all(cost[~same] == PARAMS.tau_cost)


def test_answers_do_not_depend_on_how_the_pairs_are_batched_and_each_is_computed_once():
    costs, who = frame_costs()
    ca, cb, da, db, _ = all_pairs(who)
    whole = costs.get(ca, cb, da, db)
    calls = []
    decide = costs.gates.decide
    costs.gates.decide = lambda *a: calls.append(a[0].size) or decide(*a)  # type: ignore[method-assign]
    again = costs.get(ca[::-1], cb[::-1], da[::-1], db[::-1])
    assert not calls  # every pair looked up
    assert np.array_equal(again[0], whole[0][::-1]) and np.array_equal(again[1], whole[1][::-1])
    fresh, _ = frame_costs()
    for i in range(ca.size):  # one pair at a time, in a fresh frame
        ok, cost = fresh.get(ca[i : i + 1], cb[i : i + 1], da[i : i + 1], db[i : i + 1])
        assert ok[0] == whole[0][i] and cost[0] == whole[1][i]


def test_a_pair_passing_the_gates_with_another_persons_3d_pose_fails_on_its_cost():
    """cam1's detection of person 0 carries person 1's 3D pose: its 2D geometry passes the pair
    gates, its pose cost does not (tau_cost); ok is False and the cost is capped."""
    costs, who = frame_costs(kpts3d_of=lambda cam, k: 1 if (cam == "cam1" and k == 0) else k)
    d1 = who[1].index(0)
    d0 = who[0].index(0)
    ok, cost = costs.get(np.array([0]), np.array([1]), np.array([d0]), np.array([d1]))
    assert not ok[0] and cost[0] == PARAMS.tau_cost


def test_same_track_pairs_are_the_pairs_of_one_tracks_gated_detections_in_two_cameras():
    okc = np.zeros((3, 2, 2), bool)  # (C,T,N)
    okc[0, 0, 1] = okc[1, 0, 0] = okc[2, 0, 1] = True  # track 0 in cameras 0, 1, 2
    okc[1, 1, 1] = okc[2, 1, 0] = True  # track 1 in cameras 1, 2
    okc[2, 1, 1] = True  # ... and a second detection in camera 2
    got = set(zip(*(x.tolist() for x in same_track_pairs(okc))))
    assert got == {(0, 1, 1, 0), (0, 2, 1, 1), (1, 2, 0, 1), (1, 2, 1, 0), (1, 2, 1, 1)}
