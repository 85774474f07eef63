"""The method, pure numpy/scipy (never imports rclpy), laid out by its stages:

- ``geometry``: cameras, rigs, rig file formats, DLT, Procrustes, frames;
- ``association``: MAEM stage 2 (pair gates, clustering);
- ``triangulation``: MAEM stage 3 (per-keypoint RANSAC);
- ``tracking``: persistent ids and track-assisted association;
- ``sync``: approximate-time synchroniser of per-camera messages;
- ``interchange``: scene folders, SAM 3D Body npz, xrmocap ground truth;
- ``metrics``: the paper's pose metrics and identity metrics;
- shared types and rules: ``detections`` (FrameDetections), ``skeleton`` (keypoint
  conventions), ``paramspec`` (one definition per parameter), ``limits``, ``errors``, ``jit``,
  ``intsets``, ``colors``.
"""
