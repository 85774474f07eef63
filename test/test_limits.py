"""Per-message bounds (core/limits.py) and the one input-error type (core/errors.py)."""
from __future__ import annotations

import numpy as np
import pytest

from maem_ros.core.errors import InputError
from maem_ros.core.interchange import MissingDataError
from maem_ros.core.limits import (InputLimits, LimitError, check_clusters, check_detections,
                                  mask_far_joints)
from maem_ros.ros.wire import WireError
from maem_ros.sim.rigs import build_rig


@pytest.fixture(scope="module")
def rig():
    return build_rig("sportcenter6")


def test_every_input_error_carries_a_reason():
    assert WireError("/t", "f", "bad", "bad_size").reason == "bad_size"
    assert MissingDataError("x").reason == "no_data"
    assert LimitError("x").reason == "out_of_range"
    assert LimitError("x", "too_many_people").reason == "too_many_people"
    assert all(issubclass(c, InputError) and issubclass(c, ValueError)
               for c in (WireError, MissingDataError, LimitError))


def test_detections_bounds(rig):
    from maem_ros.sim.scene import Scene, SceneConfig
    scene = Scene(SceneConfig(rig="sportcenter6", frames=1, seed=1, num_vertices=100))
    dets = scene.detections("camera_0", 0)
    limits = InputLimits(max_detections=dets.n)
    check_detections(dets, rig, limits, "t")  # in bounds: no error
    with pytest.raises(LimitError, match="max_detections") as e:
        check_detections(dets, rig, InputLimits(max_detections=dets.n - 1), "t")
    assert e.value.reason == "too_many_detections"
    cam = rig["camera_0"]
    far = dets.select(np.arange(dets.n))
    far.verts2d[0, 0, 0] = 2.01 * cam.width  # beyond one image size right of the image
    with pytest.raises(LimitError, match="verts2d"):
        check_detections(far, rig, limits, "t")
    near = dets.select(np.arange(dets.n))
    near.kpts2d[0, 0, 1] = -0.99 * cam.height  # within one image size: accepted
    near.kpts2d[0, 1] = np.nan  # missing keypoint: not out of range
    check_detections(near, rig, limits, "t")


def test_clusters_bounds(rig):
    cam = np.array([0, 1, 2])
    k = np.full((3, 4, 2), 100.0)
    check_clusters(3, cam, k, rig, InputLimits(max_people=3), "t")
    with pytest.raises(LimitError) as e:
        check_clusters(4, cam, k, rig, InputLimits(max_people=3), "t")
    assert e.value.reason == "too_many_people"
    k[2, 3, 0] = 1e30
    with pytest.raises(LimitError, match="1e\\+30"):
        check_clusters(3, cam, k, rig, InputLimits(), "t")


def test_far_joints_become_nan():
    j = np.zeros((2, 3, 3))
    j[1, 2] = [0.0, 0.0, 1e30]
    j[0, 1] = [np.nan, 0, 0]
    assert mask_far_joints(j, InputLimits(world_extent_m=100.0)) == 1
    assert np.isnan(j[1, 2]).all() and np.isfinite(j[1, :2]).all()


def test_bad_limits():
    with pytest.raises(ValueError, match="max_people"):
        InputLimits(max_people=0)
    with pytest.raises(ValueError, match="world_extent"):
        InputLimits(world_extent_m=0.0)
