"""The consistent clustering's numba kernels (core/clustering_kernel.py) give the numpy paths'
results: the merge check's verdicts on candidate clusters (members padded anywhere, joints
unusable, points behind a camera, too few rays) and the cluster-level table update."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_association import ring_rig

from maem_ros.core import clustering, clustering_kernel
from maem_ros.core.association import rig_geometry
from maem_ros.core.detections import DetectionTable, FrameDetections

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
def test_numba_merge_check_equals_the_numpy_check(seed, cams, people, noise, tau):
    rng = np.random.default_rng(seed)
    rig = ring_rig(cams)
    table = _table(rig, rng, people, noise)
    P, _ = rig_geometry(rig)
    joints = np.arange(J)
    numpy_check = clustering._Verifier(table, P, joints, tau, None)
    numba_check = clustering._Verifier(table, P, joints, tau, clustering_kernel)
    N = len(table)
    rows = np.full((40, cams + 2), -1, np.int64)
    for k in range(rows.shape[0]):  # members anywhere in the row, padding in between
        members = rng.choice(N, rng.integers(1, min(N, cams + 2) + 1), replace=False)
        rows[k, rng.choice(rows.shape[1], members.size, replace=False)] = members
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
    tables = []
    for kernels in (None, clustering_kernel):
        size = np.ones(n, np.int64)
        camset = rng.random((n, 4)) < 0.5
        b, s = between.copy(), support.copy()
        clustering._absorb(x, y, size, b, s, camset.copy(), kernels)
        tables.append((b, s, size))
    for want, got in zip(*tables):
        np.testing.assert_array_equal(got, want)
