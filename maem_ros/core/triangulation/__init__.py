"""MAEM stage 3: per-keypoint RANSAC over view-pair DLT hypotheses, then a weighted DLT of the
inliers (``ransac``; its fused numba kernel in ``ransac_kernel``).

Exports: TriangulationParams, Poses, triangulate.
"""

from maem_ros.core.triangulation.ransac import Poses, TriangulationParams, triangulate

__all__ = ["Poses", "TriangulationParams", "triangulate"]
