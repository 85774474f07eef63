"""A rig's geometry as the pair gates read it (projections, fundamental matrices both ways and
as the epipolar kernels take them), computed once per Rig object and again only when a
camera's intrinsics or pose change."""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np

from maem_ros.core.association.gates.point_rows import PairMatrices, pair_matrices
from maem_ros.core.geometry.camera import Rig, fundamental_matrix


class RigGeometry(NamedTuple):
    """A rig's cached geometry (rectified pinhole px, world m)."""

    key: tuple  # the cameras' names, K_rect, R, t as bytes
    P: np.ndarray  # (C,3,4) rectified world -> px
    F: dict[tuple[int, int], np.ndarray]  # F[(a, b)], a < b, x_b^T F x_a = 0
    stack: np.ndarray  # (C,C,3,3) F[a, b] both ways (F[b, a] = F[a, b]^T), zero diagonal
    pairs: PairMatrices  # F as the epipolar kernels take them


_GEOMETRY: weakref.WeakKeyDictionary[Rig, RigGeometry] = weakref.WeakKeyDictionary()


def rig_geometry(rig: Rig) -> RigGeometry:
    """The rig's :class:`RigGeometry`, cached per Rig object (recomputed when a camera's
    name, K_rect, R or t changed)."""
    key = tuple((c.name, c.K_rect.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in rig)
    hit = _GEOMETRY.get(rig)
    if hit is not None and hit.key == key:
        return hit
    cams = rig.cameras
    P = np.stack([c.P for c in cams]) if cams else np.zeros((0, 3, 4))
    F = {
        (a, b): fundamental_matrix(cams[a], cams[b])
        for a in range(len(cams))
        for b in range(a + 1, len(cams))
    }
    stack = np.zeros((len(cams), len(cams), 3, 3))
    for (a, b), f in F.items():
        stack[a, b], stack[b, a] = f, f.T
    _GEOMETRY[rig] = hit = RigGeometry(key, P, F, stack, pair_matrices(F))
    return hit
