"""How the association runs, apart from what it decides: the kernels' backend and arithmetic,
the epipolar gate's early exit and the mesh gate's screening levels.

These settings change speed, not the method: the gates' decisions are the same on every
backend, with or without early exit, in either precision (the mixed kernel's rigorous
rounding bound), and on the screening levels unless a subset mean errs by more than its
margin (module docstring of screening). The method's thresholds are
core.association.AssociationParams; each of these fields is still one flat parameter of the
association node (core/paramspec.py), so params files and ROS parameters name them as before.
"""

from __future__ import annotations

from dataclasses import dataclass

from maem_ros.core.association.gates.epipolar_constants import BACKENDS, PRECISIONS
from maem_ros.core.paramspec import Params, param

#: overrides that decide every pair of the mesh gate on all its vertices (no screening
#: levels), as the MAEM paper does
EVERY_VERTEX = {"screen_stride": 1, "screen_coarse_stride": 1}


@dataclass
class ExecutionParams(Params):
    """Performance settings of MAEM stage 2 (px where noted); one field = one parameter of the
    association node, read from the same flat keys of a params file as the method's.

    ``backend`` selects the kernels of the gates (epipolar, reprojection), the pair cost and
    the clustering (auto = numba when installed, else numpy); both give the same decisions.
    ``epipolar_precision`` (numba): ``mixed`` float32 distances with a rigorous rounding-error
    bound (undecided pairs redone in float64; means ~1e-5 relative), ``float64`` (means
    ~1e-13).
    """

    backend: str = param(
        "auto",
        "kernels of the gates (epipolar, reprojection), the pair cost "
        "and the clustering (auto = numba when installed, else numpy)",
        choices=BACKENDS,
    )
    epipolar_precision: str = param(
        "mixed",
        "numba kernel arithmetic: mixed (float32 SIMD with "
        "a rounding-error bound, float64 decisions) or "
        "float64",
        choices=PRECISIONS,
    )
    early_exit: bool = param(True, "stop the mesh distance early once a pair cannot pass")
    screen_stride: int = param(
        8,
        "mesh gate: decide pairs on 1/n of the gate vertices (runs "
        "of 8 consecutive ones) first, on the full set only within "
        "screen_margin of tau_mesh (1 = off: every pair on the full "
        "set, the paper)",
        minimum=1,
    )
    screen_margin: float = param(
        1.0, "px, mesh gate: subset means within this of tau_mesh are decided on the full set", minimum=0.0
    )
    screen_coarse_stride: int = param(
        32,
        "mesh gate, before the screen: decide pairs on 1/n of "
        "the gate vertices (runs of 8), on the screen only "
        "within screen_coarse_margin of tau_mesh (1 = off; "
        "only with a screen, and coarser than it)",
        minimum=1,
    )
    screen_coarse_margin: float = param(
        2.5, "px, mesh gate: coarse subset means within this of tau_mesh go on to the screen", minimum=0.0
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if 1 < self.screen_coarse_stride <= self.screen_stride:
            raise ValueError(
                f"screen_coarse_stride: must be 1 (off) or coarser than "
                f"screen_stride ({self.screen_stride}), got "
                f"{self.screen_coarse_stride}"
            )

    def screen_levels(self) -> list[tuple[int, float]]:
        """(stride, margin px) of the mesh gate's screening levels, coarse to fine (empty: every
        pair on the full set)."""
        if self.screen_stride <= 1:
            return []
        levels = [(self.screen_stride, self.screen_margin)]
        if self.screen_coarse_stride > 1:
            levels.insert(0, (self.screen_coarse_stride, self.screen_coarse_margin))
        return levels
