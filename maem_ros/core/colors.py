"""The one colour scheme for person / track ids: RViz markers (ros/wire), image overlays
(frontend/overlay.py, tools/demo/demo_report.py), plots and the Foxglove view all use it, so a
player has the same colour everywhere."""

from __future__ import annotations

import colorsys

#: golden-ratio hue step: consecutive ids get well-separated hues
_HUE_STEP = 0.618033988749895
_SATURATION, _VALUE = 0.85, 0.95


def id_rgb(track_id: int) -> tuple[float, float, float]:
    """A stable colour for an integer id (track id or detection index): (r, g, b) in [0, 1]."""
    return colorsys.hsv_to_rgb((int(track_id) * _HUE_STEP) % 1.0, _SATURATION, _VALUE)


def id_bgr8(track_id: int) -> tuple[int, int, int]:
    """:func:`id_rgb` as an OpenCV colour: (b, g, r) integers in 0..255."""
    r, g, b = id_rgb(track_id)
    return int(round(255 * b)), int(round(255 * g)), int(round(255 * r))
