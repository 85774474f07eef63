"""draw_detections: boxes, labels, bones and vertex dots end up where the detections say."""
from __future__ import annotations

import colorsys

import numpy as np
import pytest

from maem_ros.core.colors import id_bgr8
from maem_ros.core.detections import FrameDetections
from maem_ros.core.skeleton import MHR70, SPORTCENTER_13
from maem_ros.frontend.overlay import draw_detections


def _dets(n: int = 2, joints: int = 13, verts: int = 200) -> FrameDetections:
    rng = np.random.default_rng(1)
    boxes, k2, vv = [], [], []
    for i in range(n):
        x0, y0 = 60 + 250 * i, 80
        boxes.append([x0, y0, x0 + 120, y0 + 300])
        k2.append(np.stack([x0 + 10 + 100 * rng.random(joints), y0 + 10 + 280 * rng.random(joints)], 1))
        vv.append(np.stack([x0 + 5 + 110 * rng.random(verts), y0 + 5 + 290 * rng.random(verts)], 1))
    return FrameDetections("cam", 1, np.array(boxes, float), np.linspace(0.95, 0.8, n),
                           np.array(k2), np.zeros((n, joints, 3)), np.array(vv, np.float32))


def test_draws_box_bones_and_keeps_input():
    img = np.zeros((480, 640, 3), np.uint8)
    dets = _dets()
    out = draw_detections(img, dets, ids=[7, -1])
    assert out.shape == img.shape and out.dtype == np.uint8
    assert not img.any(), "input image must not be modified"
    colour = np.array(id_bgr8(7))
    # a point on the left edge of box 0 has the id colour
    assert np.abs(out[200, 60].astype(int) - colour).max() <= 40
    # tentative id (-1) is grey
    assert tuple(out[200, 310]) == (160, 160, 160)
    # a bone midpoint of detection 0 is coloured
    a, b = SPORTCENTER_13.bones[-1]
    mid = 0.5 * (dets.kpts2d[0, a] + dets.kpts2d[0, b])
    patch = out[int(mid[1]) - 1:int(mid[1]) + 2, int(mid[0]) - 1:int(mid[0]) + 2]
    assert patch.any()
    # far from everything: untouched
    assert not out[470, 630].any()


def test_vertex_dots_only_when_asked():
    img = np.zeros((480, 640), np.uint8)  # mono input -> BGR output
    dets = _dets(n=1, joints=70, verts=400)
    dets.kpts2d[:] = np.nan  # no joints: only the box and the vertex dots
    without = draw_detections(img, dets, convention=MHR70)
    with_v = draw_detections(img, dets, convention="mhr70", max_vertices=100)
    assert without.shape == (480, 640, 3)
    v = np.round(dets.verts2d[0, ::4]).astype(int)
    inner = v[(v[:, 0] > 70) & (v[:, 0] < 170) & (v[:, 1] > 120) & (v[:, 1] < 370)]
    assert np.mean(with_v[inner[:, 1], inner[:, 0]].any(axis=1)) > 0.95
    assert np.mean(without[inner[:, 1], inner[:, 0]].any(axis=1)) < 0.2


def test_empty_and_bad_inputs():
    img = np.full((100, 100, 3), 9, np.uint8)
    out = draw_detections(img, FrameDetections.empty("cam", 0, 13, 0))
    assert np.array_equal(out, img) and out is not img
    with pytest.raises(ValueError, match="2 ids for 1 detections"):
        draw_detections(img, _dets(n=1), ids=[1, 2])
    with pytest.raises(ValueError, match="convention 'mhr70' has 70 joints"):
        draw_detections(img, _dets(n=1), convention="mhr70")
    with pytest.raises(ValueError, match="expected an image array"):
        draw_detections(None, _dets(n=1))
    # unknown joint count: joints drawn, no bones, no error
    assert draw_detections(img, _dets(n=1, joints=5)).any()
    # far-off and non-finite coordinates do not crash
    d = _dets(n=1)
    d.bboxes[0] = [-1e9, -1e9, 1e9, 1e9]
    d.kpts2d[0, 0] = np.inf
    draw_detections(img, d)


def test_one_id_colour_for_markers_and_overlays() -> None:
    from maem_ros.core.colors import id_rgb
    from maem_ros.ros.wire import id_color
    for track_id in (0, 1, 7, 4096):
        r, g, b = id_rgb(track_id)
        marker = id_color(track_id)
        assert (marker.r, marker.g, marker.b) == pytest.approx((r, g, b), abs=1e-6)
        assert id_bgr8(track_id) == tuple(int(round(255 * c)) for c in (b, g, r))
    # neighbouring ids are far apart in hue
    hues = [colorsys.rgb_to_hsv(*id_rgb(i))[0] for i in range(8)]
    assert min(abs(a - b) for a, b in zip(hues, hues[1:])) > 0.2
