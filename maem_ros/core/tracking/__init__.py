"""People over time: persistent ids and track-assisted association.

- ``tracks``: :class:`Tracker` (Hungarian assignment on 3D distance, constant velocity);
- ``temporal``: :class:`TemporalAssociator` (detections explained by existing 3D tracks first,
  the full MAEM association only on the rest), its parameters :class:`TemporalParams`
  (``temporal_params``) and the order of contested candidates (``contested``);
- ``track_filter`` (the track stage's Kalman root + smoothed joints) and ``track_geometry``
  (its batched projections, triangulation and cluster verification);
- ``bone_filter``: :class:`BoneLengthFilter` (bone-length plausibility on a track).

Exports: Tracker, TemporalAssociator, TemporalParams, TemporalResult, BoneLengthFilter.
"""

from maem_ros.core.tracking.bone_filter import BoneLengthFilter
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalResult
from maem_ros.core.tracking.temporal_params import TemporalParams
from maem_ros.core.tracking.tracks import Tracker

__all__ = ["BoneLengthFilter", "TemporalAssociator", "TemporalParams", "TemporalResult", "Tracker"]
