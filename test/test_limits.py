"""Per-message bounds (core/limits.py) and the one input-error type (core/errors.py)."""
from __future__ import annotations

import numpy as np
import pytest

from maem_ros.core.errors import InputError
from maem_ros.core.interchange import MissingDataError
from maem_ros.core.limits import InputLimits, LimitError, check_clusters, check_detections, mask_far_joints
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


@pytest.mark.parametrize("layout", ["f32", "q4"])
def test_a_message_is_checked_before_its_vertices_are_decoded(rig, layout):
    """read_detections + check_detection_arrays on the undecoded vertices' extremes accepts and
    rejects exactly what check_detections on the decoded FrameDetections does; the extremes
    are those of the decoded vertices and the cheap bounds contain them."""
    from maem_ros.core.limits import check_detection_arrays
    from maem_ros.ros.wire import detections_to_msg, read_detections
    from maem_ros.sim.scene import Scene, SceneConfig
    dets = Scene(SceneConfig(rig="sportcenter6", frames=1, seed=2,
                             num_vertices=300)).detections("camera_1", 0)
    cam = rig["camera_1"]
    # a small margin: the far vertices stay within what q4 carries (4096 px from the origin)
    limits = InputLimits(max_detections=dets.n, pixel_margin=0.2)
    cases = {"ok": (None, None), "far_u": ((1, 5, 0), 1.5 * cam.width),
             "far_v": ((0, 7, 1), -0.5 * cam.height), "missing": ((2, 3, 0), np.nan)}
    for name, (where, value) in cases.items():
        d = dets.select(np.arange(dets.n))
        if where is not None:
            d.verts2d[where] = value
        if name == "missing":  # one detection with no vertex at all
            d.verts2d[1] = np.nan
        msg = read_detections(detections_to_msg(d, layout), "t", rig.names)
        decoded = msg.decode()
        verts = decoded.verts2d.reshape(-1, 2)
        expected = np.array([np.nanmin(verts, axis=0), np.nanmax(verts, axis=0)])
        np.testing.assert_allclose(msg.vertex_extremes(), expected, rtol=0, atol=1e-3)
        cheap = msg.vertex_extremes(exact=False)
        assert (cheap[0] <= expected[0] + 1e-3).all() and (cheap[1] >= expected[1] - 1e-3).all()
        errors = [_limit_error(check_detections, decoded, rig, limits, "t"),
                  _limit_error(check_detection_arrays, msg.camera, msg.bboxes, msg.kpts2d,
                               msg.vertex_extremes, rig, limits, "t")]
        expected_error = None if name in ("ok", "missing") else ("out_of_range", True)
        assert errors[0] == errors[1] == expected_error, (name, errors)


def _limit_error(check, *args) -> tuple[str, bool] | None:
    """(reason, whether it names verts2d) of the LimitError ``check(*args)`` raises, or None."""
    try:
        check(*args)
    except LimitError as e:
        return e.reason, "verts2d" in str(e)
    return None
