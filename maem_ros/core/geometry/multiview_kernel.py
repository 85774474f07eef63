"""Numba pieces of the DLT's 3x3 normal-equation solve (core.geometry.multiview), compiled once
for the kernels that triangulate in their loops: the clustering's merge check, the RANSAC
triangulation and the reprojection gate (imported by them only; without numba ``jit`` leaves
the functions as they are and the numpy paths run instead).

- :func:`view_entries`: multiview.normal_entries of one view for all its points;
- :func:`cofactors`: multiview.normal_cofactors for scalars;
- :func:`adjugate`: multiview.adjugate_solve for scalars;
- ``SINGULAR``: the relative determinant below which a system is singular (multiview's).
"""

from __future__ import annotations

from maem_ros.core.geometry.multiview import SINGULAR, adjugate_solve, normal_cofactors
from maem_ros.core.jit import jit

__all__ = ["SINGULAR", "adjugate", "cofactors", "view_entries"]

# multiview's elementwise formulas, compiled for the scalars of the kernels' loops (one
# home of the arithmetic: multiview)
cofactors = jit(normal_cofactors, inline=True)
adjugate = jit(adjugate_solve, inline=True)


@jit
def view_entries(P, u, v, usable, E):
    """multiview.normal_entries of one view for all its points: P (3,4), u, v, usable (J,)
    -> E (9,J); rows r1 = u P3 - P1, r2 = v P3 - P2, uv = 0 where unusable."""
    for j in range(u.shape[0]):
        uu = u[j] if usable[j] else 0.0
        vv = v[j] if usable[j] else 0.0
        a0 = uu * P[2, 0] - P[0, 0]
        a1 = uu * P[2, 1] - P[0, 1]
        a2 = uu * P[2, 2] - P[0, 2]
        a3 = uu * P[2, 3] - P[0, 3]
        b0 = vv * P[2, 0] - P[1, 0]
        b1 = vv * P[2, 1] - P[1, 1]
        b2 = vv * P[2, 2] - P[1, 2]
        b3 = vv * P[2, 3] - P[1, 3]
        E[0, j] = a0 * a0 + b0 * b0
        E[1, j] = a0 * a1 + b0 * b1
        E[2, j] = a0 * a2 + b0 * b2
        E[3, j] = a1 * a1 + b1 * b1
        E[4, j] = a1 * a2 + b1 * b2
        E[5, j] = a2 * a2 + b2 * b2
        E[6, j] = a0 * a3 + b0 * b3
        E[7, j] = a1 * a3 + b1 * b3
        E[8, j] = a2 * a3 + b2 * b3
