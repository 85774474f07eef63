"""The parameters of MAEM stage 2: :class:`AssociationParams` (the method's thresholds and
switches) holding :class:`ExecutionParams` (how it runs: core.association.gates), and the
overrides that give the MAEM paper's pipeline."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from maem_ros.core.association.gates.execution import EVERY_VERTEX, ExecutionParams
from maem_ros.core.paramspec import Params, param
from maem_ros.core.skeleton import joint_subset

#: clustering methods (core.association.clustering)
CLUSTERING_METHODS = ("consistent", "paper", "spectral")

#: overrides that give the MAEM paper's pipeline exactly: PA-MPJPE on every keypoint, no cost
#: cap, every pair's mesh distance over all vertices, per-pair Hungarian + union-find +
#: conflict removal (flat parameter names: AssociationParams.replaced / from_mapping)
PAPER_PIPELINE = {
    "clustering": "paper",
    "cost_joints": "all",
    "tau_cost": 0.0,
    "cost_epipolar_weight": 0.0,
    **EVERY_VERTEX,
}


@dataclass
class AssociationParams(Params):
    """Thresholds (px, m, score) and switches of MAEM stage 2 -- the method; one field = one
    parameter of the association node (core/paramspec.py: add a field with ``param()`` and it
    is validated, read from params files and declared, with --help, by the node).

    ``execution`` holds how it runs (kernels' backend and precision, early exit, the mesh
    gate's subset levels: gates.ExecutionParams), settings that change speed and not the
    decisions. Its fields are flat parameters too: :meth:`from_mapping` reads both groups from
    the same flat keys (old params files load unchanged) and from an ``execution`` sub-mapping.
    ``cost_joints``: "body" (the 13 sportcenter body joints of the detections'
    keypoint convention), "all", or comma-separated keypoint indices.
    ``tau_cost`` (m): pairs whose cost is above it never match; 0 = no cap (the paper).
    ``cost_epipolar_weight`` (m) adds the pair's mean epipolar distance, as a fraction of
    tau_mesh (so the term scales with the gate: mesh px, keypoint px), to its cost.
    ``tau_verify`` (px), ``min_support`` (fraction): the consistent clustering's merge checks.
    """

    tau_det: float = param(0.9, "detection score threshold", minimum=0.0, maximum=1.0)
    tau_reproj_bbox: float = param(
        10.0, "px, bbox-centre reprojection gate", minimum=0.0, exclusive_minimum=True
    )
    tau_mesh: float = param(8.0, "px, dense-mesh epipolar gate", minimum=0.0, exclusive_minimum=True)
    k_min: int = param(4, "minimum views per cluster", minimum=2)
    reproj_gate: bool = param(True, "apply the bbox-centre reprojection gate")
    reproj_reduce: str = param("mean", "reprojection error of the pair", choices=("mean", "max"))
    epipolar_gate: str = param("mesh", "epipolar gate", choices=("mesh", "sparse", "none"))
    epipolar_distance: str = param(
        "symmetric", "point-to-line distance direction", choices=("symmetric", "forward")
    )
    vertex_stride: int = param(1, "use every n-th mesh vertex", minimum=1)
    vertex_count: int = param(0, "use at most this many vertices (0 = all)", minimum=0)
    clustering: str = param(
        "consistent",
        "consistent (verified best-first merges), paper "
        "(Hungarian + union-find) or spectral (PA-MPJPE "
        "matching baseline)",
        choices=CLUSTERING_METHODS,
    )
    cost_joints: str = param(
        "body", "pair-cost keypoints: body (13 body joints), all, or comma-separated indices"
    )
    tau_cost: float = param(0.21, "m, pairs whose cost is above this never match (0 = no cap)", minimum=0.0)
    cost_epipolar_weight: float = param(
        0.04, "m added to the pair cost per tau_mesh of mean epipolar distance", minimum=0.0
    )
    tau_verify: float = param(
        10.0,
        "px, consistent merges: each member's median reprojection error of the triangulated body joints",
        minimum=0.0,
        exclusive_minimum=True,
    )
    min_support: float = param(
        0.6, "consistent merges: fraction of cross pairs that passed the gates", minimum=0.0, maximum=1.0
    )
    #: how it runs (not a parameter itself: its fields are)
    execution: ExecutionParams = field(default_factory=ExecutionParams)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.clustering == "consistent" and self.tau_cost == 0:
            raise ValueError("tau_cost: the consistent clustering needs a cost cap > 0 m")
        joint_subset(self.cost_joints, None)
        if not isinstance(self.execution, ExecutionParams):
            raise ValueError(f"execution: expected ExecutionParams, got {type(self.execution).__name__}")

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> AssociationParams:
        """An instance from the known keys of a params dict (others are ignored); validated.
        The execution settings are read from the same flat keys (as the node declares them
        and params files have always named them) and from an optional ``execution``
        sub-mapping (which wins where both give one)."""
        nested = d.get("execution")
        if nested is not None and not isinstance(nested, Mapping):
            raise ValueError(f"execution: expected a mapping of execution settings, got {nested!r}")
        execution = ExecutionParams.from_mapping({**d, **(nested or {})})
        return cls(**{s.name: d[s.name] for s in cls.specs() if s.name in d}, execution=execution)

    def as_mapping(self) -> dict[str, Any]:
        """Every parameter by its flat name (the method's and the execution settings)."""
        return {**super().as_mapping(), **self.execution.as_mapping()}

    def replaced(self, overrides: Mapping[str, Any]) -> AssociationParams:
        """A copy with ``overrides`` (flat names of either group, e.g. PAPER_PIPELINE)."""
        return type(self).from_mapping({**self.as_mapping(), **overrides})
