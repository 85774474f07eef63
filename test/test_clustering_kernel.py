"""The consistent clustering's numba kernels (core/association/clustering_kernel.py) give the numpy paths'
results: the merge check's verdicts on candidate clusters (members padded anywhere, joints
unusable, points behind a camera, too few rays), the cluster-level table update, and the
greedy merge rounds (labels and stats, on random tables with tied gains and refused merges,
and on bench frame sets)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from maem_ros.core.association import AssociationParams, associate, clustering, clustering_kernel
from maem_ros.core.association.gates import rig_geometry
from maem_ros.core.detections import (
    PASSED,
    REJECTED_COST,
    REJECTED_EPIPOLAR,
    DetectionTable,
    FrameDetections,
    PairSet,
)
from maem_ros.core.skeleton import joint_subset
from maem_ros.core.synthetic import body_template, make_frame
from maem_ros.tools.bench.bench_load import load_bench_rig

from helpers_scene import ring_rig

pytestmark = pytest.mark.skipif(not clustering_kernel.have_numba(), reason="numba not installed")
J = 13


def _table(rig, rng: np.random.Generator, people: int, noise_px: float) -> DetectionTable:
    """Every camera sees every person (joints projected with pixel noise, some missing) plus
    one detection of random pixels."""
    bodies = rng.uniform(-3, 3, (people, 1, 3)) * [1, 1, 0] + [0, 0, 0.9] \
        + rng.uniform(-1, 1, (people, J, 3)) * [0.2, 0.12, 0.85]
    frames = {}
    for c, cam in enumerate(rig.cameras):
        uv = np.stack([cam.project_rectified(b) for b in bodies])
        uv = np.concatenate([uv, rng.uniform(0, 1280, (1, J, 2))])
        uv += rng.normal(0.0, noise_px, uv.shape)
        uv[rng.random(uv.shape[:2]) < 0.1] = np.nan
        n = uv.shape[0]
        box = np.concatenate([np.nanmin(uv, 1), np.nanmax(uv, 1)], axis=1)
        frames[c] = FrameDetections(cam.name, 0, box, np.ones(n), uv, np.zeros((n, J, 3)),
                                    np.zeros((n, 0, 2), np.float32))
    return DetectionTable.build(frames, len(rig))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), cams=st.integers(3, 6), people=st.integers(1, 4),
       noise=st.sampled_from([0.5, 4.0, 40.0]), tau=st.sampled_from([2.0, 8.0, 30.0]))
# a row whose members sit after the longest row's member count (the numpy check dropped them)
@example(seed=76103, cams=5, people=4, noise=0.5, tau=30.0)
def test_numba_merge_check_equals_the_numpy_check(seed, cams, people, noise, tau):
    rng = np.random.default_rng(seed)
    rig = ring_rig(cams)
    table = _table(rig, rng, people, noise)
    P = rig_geometry(rig).P
    joints = np.arange(J)
    numpy_check = clustering._Verifier(table, P, joints, tau, None)
    numba_check = clustering._Verifier(table, P, joints, tau, clustering_kernel)
    N = len(table)
    rows = np.full((40, cams + 2), -1, np.int64)
    for k in range(rows.shape[0]):  # members anywhere in the row, padding in between
        members = rng.choice(N, rng.integers(1, min(N, cams + 2) + 1), replace=False)
        rows[k, rng.choice(rows.shape[1], members.size, replace=False)] = members
    # the same DLT shares, bit for bit (unusable joints and the padding row weigh 0)
    np.testing.assert_array_equal(numba_check.E, numpy_check.E)
    assert not numba_check.E[:, ~numba_check.usable].any()
    want = numpy_check(rows)
    assert np.array_equal(numba_check(rows), want)
    truth = np.stack([table.offsets[:-1] + p for p in range(people)])  # (people, cams)
    assert np.array_equal(numba_check(truth), numpy_check(truth))
    if noise < tau / 2:  # the true people pass at low noise
        assert numba_check(truth).all()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(2, 30), merges=st.integers(1, 8))
def test_numba_table_update_equals_the_numpy_update(seed, n, merges):
    rng = np.random.default_rng(seed)
    merges = min(merges, n // 2)
    picked = rng.choice(n, 2 * merges, replace=False)
    x, y = picked[:merges], picked[merges:]
    between = rng.normal(size=(n, n))
    between = between + between.T
    support = rng.integers(0, 5, (n, n))
    support = support + support.T
    want = between.copy(), support.copy()
    clustering._absorb(x, y, np.ones(n, np.int64), *want, rng.random((n, 4)) < 0.5)
    got = between.copy(), support.copy()
    clustering_kernel.absorb(x, y, *got)
    for w, g in zip(want, got):
        np.testing.assert_array_equal(g, w)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(0, 60), levels=st.integers(1, 6))
def test_radix_order_equals_numpys_stable_argsort(seed, n, levels):
    """Ties (few distinct values) keep index order; values from 1e-300 to 1e300."""
    rng = np.random.default_rng(seed)
    g = np.exp(rng.choice(rng.normal(0.0, 200.0, levels), n))
    assert np.array_equal(clustering_kernel._descending_order(g), np.argsort(-g, kind="stable"))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(2, 40), edges=st.integers(0, 80))
def test_sequential_disjoint_pass_equals_the_numpy_rounds(seed, n, edges):
    rng = np.random.default_rng(seed)
    a = rng.integers(0, n - 1, edges)
    b = a + 1 + rng.integers(0, n - 1 - a)  # a < b < n, repeats allowed
    order = rng.permutation(edges)
    alive = rng.random(edges) < 0.8
    got = clustering_kernel._take_disjoint(a, b, order, alive, n)
    live = order[alive[order]]
    assert np.array_equal(got, live[clustering._disjoint_greedy(a[live], b[live], n)])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(2, 40), links=st.integers(0, 200))
def test_link_relabelling_equals_the_numpy_relabelling(seed, n, links):
    rng = np.random.default_rng(seed)
    a = rng.integers(0, n - 1, links)
    codes = np.unique(a * n + a + 1 + rng.integers(0, n - 1 - a))
    into = np.arange(n)
    moved = rng.random(n) < 0.4
    into[moved] = rng.integers(0, n, moved.sum())
    into = into[into]  # as after merges: a label maps to one that stays
    assert np.array_equal(clustering_kernel._relabel_links(codes, into, n),
                          clustering._relabel_links(codes, into, n))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(2, 40), k=st.integers(0, 10))
def test_candidate_members_are_listed_as_numpy_lists_them(seed, n, k):
    """The check's DLT sums run over the members in this order."""
    rng = np.random.default_rng(seed)
    label = rng.integers(0, n, n)
    labels = np.unique(label)
    if labels.size < 2:
        return
    pick = np.array([rng.choice(labels, 2, replace=False) for _ in range(k)],
                    np.int64).reshape(k, 2)
    got = clustering_kernel._member_rows(pick[:, 0].copy(), pick[:, 1].copy(), label)
    want = clustering._members_padded(label, [pick[:, 0], pick[:, 1]])
    assert np.array_equal(got, want)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(1, 60), k=st.integers(1, 20))
def test_sums_per_cluster_add_each_clusters_columns_in_ascending_order(seed, n, k):
    """clustering._cluster_sums, numpy and numba: bit for bit the sequential sums (float
    gains: order matters), and the matmul's counts for a bool table."""
    rng = np.random.default_rng(seed)
    gain = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-3, 4, (n, n))
    gated = rng.random((n, n)) < rng.random()
    label = rng.integers(0, k, n)
    want = np.zeros((n, k))
    for i in range(n):
        for j in range(n):
            want[i, label[j]] += gain[i, j]
    Z = np.zeros((n, k))
    Z[np.arange(n), label] = 1.0
    for kernels in (None, clustering_kernel):
        assert np.array_equal(clustering._cluster_sums(gain, label, k, kernels), want)
        assert np.array_equal(clustering._cluster_sums(gated, label, k, kernels),
                              gated.astype(float) @ Z)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(1, 40), k=st.integers(1, 12),
       cams=st.integers(1, 5))
def test_numba_move_scores_equal_the_numpy_scores(seed, n, k, cams):
    """clustering._move_scores, numpy and numba: the same best move into a cluster (the first
    of tied ones; -inf and cluster 0 when none is allowed) and out of it, on tables with
    tied gains (a coarse grid), empty and refused clusters, shared cameras and support
    below the minimum."""
    rng = np.random.default_rng(seed)
    label = rng.integers(0, k, n)
    G = rng.integers(-4, 5, (n, k)) / 4.0
    S = rng.integers(0, 4, (n, k)).astype(float)
    size = np.bincount(label, minlength=k).astype(float)
    cam = rng.integers(0, cams, n)
    camset = np.zeros((k, cams), bool)
    camset[label, cam] = True
    refused = rng.random((n, k)) < 0.2
    want = clustering._move_scores(G, S, label, camset, cam, refused, size, 0.5)
    got = clustering._move_scores(G, S, label, camset, cam, refused, size, 0.5,
                                  clustering_kernel)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def _pairs(table: DetectionTable, rng: np.random.Generator, people: int, tau: float) -> PairSet:
    """Every cross-camera pair: same-person pairs mostly pass, the others mostly fail a gate;
    costs on a 1 cm grid (ties in the gains and their sums)."""
    i, j = np.triu_indices(len(table), 1)
    i, j = i[table.cam[i] != table.cam[j]], j[table.cam[i] != table.cam[j]]
    slot = np.arange(len(table)) - table.offsets[table.cam]  # person index in its camera
    same = (slot[i] == slot[j]) & (slot[i] < people)
    stage = np.where(rng.random(i.size) < np.where(same, 0.9, 0.15), PASSED,
                     rng.choice([REJECTED_COST, REJECTED_EPIPOLAR], i.size))
    cost = np.where(stage == REJECTED_EPIPOLAR, np.nan,
                    rng.integers(0, 3 * round(tau * 100), i.size) / 100)
    stage = np.where((stage == PASSED) & (cost > tau), REJECTED_COST, stage)
    nan = np.full(i.size, np.nan)
    return PairSet(i, j, stage, nan, nan, cost)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10**6), cams=st.integers(2, 7), people=st.integers(1, 6),
       tau=st.sampled_from([0.0, 0.05, 0.08]))
def test_numba_gain_tables_equal_the_numpy_tables(seed, cams, people, tau):
    rng = np.random.default_rng(seed)
    table = _table(ring_rig(cams), rng, people, 1.0)
    pairs = _pairs(table, rng, people, 0.08)
    want = clustering._gain_matrix(table, pairs, tau, None)
    got = clustering._gain_matrix(table, pairs, tau, clustering_kernel)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), cams=st.integers(2, 7), people=st.integers(1, 6),
       noise=st.sampled_from([0.5, 4.0, 40.0]), tau=st.sampled_from([2.0, 8.0, 30.0]),
       min_support=st.sampled_from([0.0, 0.4, 0.6, 1.0]))
def test_numba_merge_rounds_equal_the_numpy_rounds(seed, cams, people, noise, tau, min_support):
    """Same labels and the same merge / refusal counts (refused merges remembered across
    rounds), and the same local moves after them."""
    rng = np.random.default_rng(seed)
    rig = ring_rig(cams)
    table = _table(rig, rng, people, noise)
    pairs = _pairs(table, rng, people, 0.08)
    P = rig_geometry(rig).P
    params = AssociationParams(tau_cost=0.08, min_support=min_support, tau_verify=tau)
    gain, geometric = clustering._gain_matrix(table, pairs, params.tau_cost)
    out = []
    for kernels in (None, clustering_kernel):
        verify = clustering._Verifier(table, P, np.arange(J), tau, kernels)
        stats = {"merges": 0.0, "merges_rejected": 0.0, "moves": 0.0}
        label = clustering._greedy_merges(table, pairs, gain, geometric, np.arange(len(table)),
                                          verify, params, stats, kernels)
        moved = clustering._local_moves(table, gain, geometric, label.copy(), verify, params,
                                        stats, kernels)
        out.append((label, moved, stats))
    (want, want_moved, want_stats), (got, got_moved, got_stats) = out
    assert np.array_equal(got, want)
    assert np.array_equal(got_moved, want_moved)
    assert got_stats == want_stats


@pytest.fixture(scope="module")
def bench_frames():
    """Frame sets of the bench load on two rigs (crowded ring, standard sportcenter)."""
    rng = np.random.default_rng(3)
    template = body_template(2000, 70, seed=0)
    sets = []
    for name, players, extras in (("ring16", 22, 3), ("sportcenter6", 10, 2)):
        rig = load_bench_rig(name)
        sets += [(rig, make_frame(rig, template, rng, players, extras).frames) for _ in range(2)]
    return sets


@pytest.mark.slow
def test_numba_and_numpy_clusterings_agree_on_bench_frames(bench_frames):
    """The consistent clustering of each frame set's gated pairs: the same groups and stats
    with the numba kernels as with the numpy paths (and merges refused on the way)."""
    rejected = 0.0
    for rig, frames in bench_frames:
        params = AssociationParams()
        result = associate(rig, frames, params)
        P = rig_geometry(rig).P
        joints = joint_subset(params.cost_joints, result.table.num_joints)
        found = []
        for backend in ("numpy", "numba"):
            stats = dict.fromkeys(("merges", "merges_rejected", "moves"), 0.0)
            groups = clustering.cluster(result.table, result.pairs, P, joints,
                                        AssociationParams.from_mapping({"backend": backend}), stats, None).groups
            found.append(([g.tolist() for g in groups], stats))
        assert found[1] == found[0]
        assert found[0][1]["merges"] > 0
        rejected += found[0][1]["merges_rejected"]
    assert rejected > 0
