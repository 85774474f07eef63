"""Triangulation's left_right option: views whose left/right labels are swapped are relabelled."""
from __future__ import annotations

import numpy as np
import pytest
from helpers_scene import project_detections, ring_rig

from maem_ros.core.association.pipeline import Cluster
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.detections import FrameDetections
from maem_ros.core.skeleton import BLAZEPOSE_33, SPORTCENTER_13
from maem_ros.core.triangulation.ransac import TriangulationParams, mirror_permutation, triangulate


def body(rng) -> np.ndarray:
    """(33,3) world metres, left side at +x (clearly asymmetric so a swap is visible)."""
    X = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 1.8], size=(33, 3))
    names = BLAZEPOSE_33.names
    for i, n in enumerate(names):
        if n.startswith("left"):
            X[i, 0] += 0.25
        elif n.startswith("right"):
            X[i, 0] -= 0.25
    return X


@pytest.fixture
def scene():
    rng = np.random.default_rng(3)
    rig = ring_rig(4, radius=4.0, height=2.0, angles=np.radians([0, 70, 160, 250]),
                   size=(1280, 720), prefix="c")
    return rig, body(rng)


def frames_of(rig: Rig, X: np.ndarray, swapped: set[str], scores=None) -> dict[str, FrameDetections]:
    """One exact detection of body X per camera; the cameras in ``swapped`` label its left and
    right keypoints the other way round."""
    perm = mirror_permutation(33)
    return {cam.name: project_detections(cam, (X[perm] if cam.name in swapped else X)[None],
                                         scores=0.9 if scores is None else scores[k])
            for k, cam in enumerate(rig)}


def test_mirror_permutation():
    perm = mirror_permutation(33)
    names = BLAZEPOSE_33.names
    assert names[perm[names.index("left_wrist")]] == "right_wrist"
    assert names[perm[names.index("mouth_left")]] == "mouth_right"
    assert perm[0] == 0  # nose
    assert np.array_equal(perm[perm], np.arange(33))
    sc = mirror_permutation(13)
    assert SPORTCENTER_13.names[sc[5]] == "right_wrist"


def test_one_swapped_view_of_four_is_relabelled(scene):
    rig, X = scene
    frames = frames_of(rig, X, {"c2"})
    cluster = [Cluster(members=[[0, 0], [1, 0], [2, 0], [3, 0]], costs=np.zeros(4))]
    on = triangulate(rig, frames, cluster, TriangulationParams(left_right=True))
    np.testing.assert_allclose(on.joints[0], X, atol=1e-6)
    assert on.mirrored[0].tolist() == [False, False, True, False]
    assert on.inliers[0].min() == 4  # every view agrees once relabelled
    off = triangulate(rig, frames, cluster, TriangulationParams())
    assert off.mirrored is None
    # the paper's variant: the swapped view is an outlier for every sided joint
    sided = np.array([n.startswith(("left", "right")) for n in BLAZEPOSE_33.names])
    assert off.inliers[0][sided].max() == 3


def test_two_views_flip_the_less_confident(scene):
    rig, X = scene
    frames = frames_of(rig, X, {"c1"}, scores=[0.9, 0.6, 0.9, 0.9])
    cluster = [Cluster(members=[[0, 0], [1, 0]], costs=np.zeros(2))]
    on = triangulate(rig, frames, cluster, TriangulationParams(left_right=True))
    assert on.mirrored[0].tolist() == [False, True]
    np.testing.assert_allclose(on.joints[0], X, atol=1e-6)


def test_consistent_views_are_left_alone(scene):
    rig, X = scene
    frames = frames_of(rig, X, set())
    cluster = [Cluster(members=[[0, 0], [1, 0], [2, 0]], costs=np.zeros(3)),
               Cluster(members=[[3, 0]], costs=np.zeros(1))]
    on = triangulate(rig, frames, cluster, TriangulationParams(left_right=True))
    assert not on.mirrored.any()
    np.testing.assert_allclose(on.joints[0], X, atol=1e-6)
    assert np.isnan(on.joints[1]).all()  # one view: nothing to triangulate


def test_left_right_param_validated():
    with pytest.raises(ValueError, match="left_right: expected true/false"):
        TriangulationParams.from_mapping({"left_right": "yes"})
    assert TriangulationParams.from_mapping({"left_right": True}).left_right is True
