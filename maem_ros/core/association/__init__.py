"""MAEM stage 2: cross-view association of one frame set's detections into people.

- ``gates``: the pair gates (bbox-centre reprojection, dense-mesh epipolar distance) behind
  one interface (PairGates: prepare each camera frame, decide a frame set's pairs) and the
  execution settings (ExecutionParams);
- ``clustering``: gated pairs -> clusters (the consistent clustering) and its numba kernel;
  ``clustering_groups``: the paper's per-pair Hungarian + union-find and the spectral baseline;
- ``params``: :class:`AssociationParams` (the method's thresholds, holding its
  ExecutionParams) and PAPER_PIPELINE;
- ``pipeline``: :func:`associate` (frames keyed by camera -> :class:`AssociationResult`).

Exports: AssociationParams, AssociationResult, ExecutionParams, PAPER_PIPELINE, PairGates,
associate, warmup.
"""

from maem_ros.core.association.gates import ExecutionParams, PairGates
from maem_ros.core.association.params import PAPER_PIPELINE, AssociationParams
from maem_ros.core.association.pipeline import AssociationResult, associate, warmup

__all__ = [
    "PAPER_PIPELINE",
    "AssociationParams",
    "AssociationResult",
    "ExecutionParams",
    "PairGates",
    "associate",
    "warmup",
]
