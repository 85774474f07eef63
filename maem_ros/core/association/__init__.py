"""MAEM stage 2: cross-view association of one frame set's detections into people.

- ``gates``: the pair gates (bbox-centre reprojection, dense-mesh epipolar distance) and the
  PA-MPJPE pose cost that rank and filter cross-view detection pairs;
- ``clustering``: gated pairs -> clusters (the consistent clustering, or the paper's per-pair
  Hungarian + union-find) and its numba kernel;
- ``pipeline``: :func:`associate` (frames keyed by camera -> :class:`AssociationResult`) and
  :class:`AssociationParams`.

Exports: AssociationParams, AssociationResult, associate, warmup.
"""
from maem_ros.core.association.pipeline import (AssociationParams, AssociationResult, associate,
                                                warmup)

__all__ = ["AssociationParams", "AssociationResult", "associate", "warmup"]
