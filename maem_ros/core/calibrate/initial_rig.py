"""Initial rig from pairwise relative poses: a maximum spanning tree over the camera graph
(edge weight = shared evidence), then a check of every estimated pair against the tree.

Frame: camera ``root``'s camera frame, metres from the skeletons. Poses world -> camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .correspondence import MIN_SUPPORT, PairEstimate

#: a pair whose own estimate disagrees with the rig by more than this is reported
PAIR_CHECK_DEG = 5.0


@dataclass
class InitialRig:
    """R (C,3,3), t (C,3) world -> camera (NaN for cameras not connected), the tree's edges
    (a, b), ``weak_pairs`` [(a, b, support)] under MIN_SUPPORT, ``disagreeing`` [(a, b, deg)]
    pairs whose own estimate disagrees with the rig."""

    R: np.ndarray
    t: np.ndarray
    edges: list[tuple[int, int]]
    weak_pairs: list[tuple[int, int, int]] = field(default_factory=list)
    disagreeing: list[tuple[int, int, float]] = field(default_factory=list)

    @property
    def connected(self) -> np.ndarray:
        return np.all(np.isfinite(self.t), axis=1)


def rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) of the rotation Ra Rb^T."""
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def initial_rig(num_cameras: int, pairs: list[PairEstimate], root: int = 0) -> InitialRig:
    """Chain the best-supported pairs from ``root`` (Kruskal on support, largest first)."""
    C = num_cameras
    good = [p for p in pairs if p.support >= MIN_SUPPORT and np.all(np.isfinite(p.t))]
    weak = [(p.a, p.b, p.support) for p in pairs if p not in good]
    parent = list(range(C))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    tree: list[PairEstimate] = []
    for p in sorted(good, key=lambda p: -p.support):
        ra, rb = find(p.a), find(p.b)
        if ra != rb:
            parent[ra] = rb
            tree.append(p)
    R = np.full((C, 3, 3), np.nan)
    t = np.full((C, 3), np.nan)
    R[root], t[root] = np.eye(3), np.zeros(3)
    placed = {root}
    grew = True
    while grew:
        grew = False
        for p in tree:
            if p.a in placed and p.b not in placed:
                # X_a = R_ab X_b + t_ab  ->  R_b = R_ab^T R_a, t_b = R_ab^T (t_a - t_ab)
                R[p.b] = p.R.T @ R[p.a]
                t[p.b] = p.R.T @ (t[p.a] - p.t)
                placed.add(p.b)
                grew = True
            elif p.b in placed and p.a not in placed:
                R[p.a] = p.R @ R[p.b]
                t[p.a] = p.t + p.R @ t[p.b]
                placed.add(p.a)
                grew = True
    rig = InitialRig(R=R, t=t, edges=[(p.a, p.b) for p in tree], weak_pairs=weak)
    for p in good:
        if p.a in placed and p.b in placed:
            deg = rotation_deg(R[p.a] @ R[p.b].T, p.R)
            if deg > PAIR_CHECK_DEG:
                rig.disagreeing.append((p.a, p.b, deg))
    return rig
