"""The track stage's parameters (core/tracking/temporal.py; px, m, s, frames): one field = one
parameter of the association node (core/paramspec.py)."""

from __future__ import annotations

from dataclasses import dataclass

from maem_ros.core.paramspec import Params, param

#: epipolar test inside a track's cluster: the association's own (default: its ``epipolar_gate``,
#: so the track stage keeps every view the association would, and a keypoint-only frontend (no
#: mesh: every mesh test fails) keeps its views; doc/tracking.md), the mesh vertices, the 2D
#: keypoints (cheaper, but noisy keypoints fail it: views dropped from tracked people), or none
VERIFY_EPIPOLAR = ("association", "sparse", "mesh", "none")


@dataclass
class TemporalParams(Params):
    """Tracking stage of the association node (px, m, s, frames; module docstring); one field =
    one parameter of the association node (core/paramspec.py)."""

    temporal: bool = param(
        True, "track-assisted association (off = the per-frame paper pipeline, no track ids)"
    )
    confirm_hits: int = param(3, "supported frames before a track gets an id", minimum=1)
    max_misses: int = param(10, "frames a track survives without support", minimum=0)
    max_gap_s: float = param(
        1.0, "s, a forward stamp jump beyond this ends all tracks", minimum=0.0, exclusive_minimum=True
    )
    gate_px: float = param(
        25.0,
        "px, base gate of a detection's body keypoints vs a track's "
        "projected predicted joints (median distance)",
        minimum=0.0,
        exclusive_minimum=True,
    )
    gate_sigma: float = param(3.0, "gate growth per projected root std (px per px)", minimum=0.0)
    gate_max_px: float = param(80.0, "px, cap of the track gate", minimum=0.0, exclusive_minimum=True)
    refine_px: float = param(
        20.0,
        "px, gate of the second assignment against each verified cluster's own triangulation (0 = off)",
        minimum=0.0,
    )
    pose_weight: float = param(
        100.0,
        "px per m of pose cost added to a contested assignment's "
        "cost: pair cost vs the track's other views, else "
        "PA-MPJPE vs the track",
        minimum=0.0,
    )
    min_track_views: int = param(
        2, "views a confirmed track may be updated from (below k_min: flagged)", minimum=2
    )
    one_view: bool = param(True, "keep a confirmed track alive on one view + its prediction")
    one_view_std: float = param(
        0.3, "m, root measurement std of a one-view update", minimum=0.0, exclusive_minimum=True
    )
    verify_epipolar: str = param(
        "association",
        "epipolar test inside a track's cluster: the "
        "association's epipolar_gate, mesh vertices, 2D "
        "keypoints (sparse) or none",
        choices=VERIFY_EPIPOLAR,
    )
    light_new_every: float = param(
        0.1,
        "s, a light step (a node falling behind) associates the "
        "detections no track explains (new people) only when the last "
        "frame set that did is this long ago or more; 0 = every light step",
        minimum=0.0,
    )
    reid_m: float = param(
        0.5,
        "m, a new cluster this close to a track re-acquires / merges it",
        minimum=0.0,
        exclusive_minimum=True,
    )
    accel_std: float = param(
        4.0, "m/s^2, process noise of the root Kalman filter", minimum=0.0, exclusive_minimum=True
    )
    meas_std: float = param(0.03, "m, root measurement std", minimum=0.0, exclusive_minimum=True)
    joint_alpha: float = param(
        0.6,
        "weight of the newest pose in the per-joint smoothing",
        minimum=0.0,
        maximum=1.0,
        exclusive_minimum=True,
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.gate_max_px < self.gate_px:
            raise ValueError(f"gate_max_px: {self.gate_max_px} is below gate_px {self.gate_px}")
