"""The cross-view pair gates of MAEM stage 2, behind one interface (:class:`PairGates`):
the bbox-centre reprojection gate and the epipolar gate (mean point-to-epipolar-line distance
over the dense mesh vertices, or over the 2D keypoints), with their numba kernels.

- ``PairGates(rig, params).prepare(frame)``: per camera frame as it arrives, the mesh gate's
  per-frame data (screening subsets copied contiguous, block ranges), kept by the gates;
  ``prepare_scanning(frame)`` the same for a frame nobody checked yet, with what its pass
  found (:class:`VertexScan`: the first infinite vertex, the extremes);
- ``PairGates.candidates(table)`` / ``PairGates.frame_set(frames).decide(...)``: per frame
  set, every candidate pair's stage (passed, or the gate that rejected it) and mean epipolar
  distance (:class:`GateDecisions`);
- :class:`ExecutionParams`: how the gates (and the association) run: backend, precision,
  early exit, screening levels; ``EVERY_VERTEX``: its overrides for the paper's full mesh;
- :func:`rig_geometry`: a rig's projections and fundamental matrices, cached;
- :func:`warmup`: compile the kernels before the first frame.

Modules: ``pair_gates`` (the interface), ``reprojection`` (+ ``reprojection_kernel``),
``epipolar`` (sums; + ``epipolar_kernel``), ``screening`` (the mesh gate's levels),
``point_rows`` (how the kernels read points), ``epipolar_constants``, ``execution``,
``rig_geometry``.

Exports: EPIPOLAR_GATES, EVERY_VERTEX, ExecutionParams, FrameSet, GateDecisions, PairGates,
RigGeometry, VertexScan, gate_columns, rig_geometry, warmup.
"""

from maem_ros.core.association.gates.execution import EVERY_VERTEX, ExecutionParams
from maem_ros.core.association.gates.pair_gates import (
    EPIPOLAR_GATES,
    FrameSet,
    GateDecisions,
    PairGates,
    VertexScan,
    gate_columns,
    warmup,
)
from maem_ros.core.association.gates.rig_geometry import RigGeometry, rig_geometry

__all__ = [
    "EPIPOLAR_GATES",
    "EVERY_VERTEX",
    "ExecutionParams",
    "FrameSet",
    "GateDecisions",
    "PairGates",
    "RigGeometry",
    "VertexScan",
    "gate_columns",
    "rig_geometry",
    "warmup",
]
