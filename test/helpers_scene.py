"""Constructed scenes shared by the unit tests: exact pinhole cameras (no distortion, K_rect = K)
on a ring around the court, and FrameDetections made by projecting known 3D points through them,
so every expected answer is known by construction.

World frame: z up, metres, court centre at the origin. Image coordinates: rectified px.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig


def look_at(name: str, eye, target=(0.0, 0.0, 1.0), f: float = 1000.0,
            size: tuple[int, int] = (1280, 960)) -> Camera:
    """A distortion-free camera ``name`` at ``eye`` (world m) looking at ``target``, image x
    horizontal (world z up), focal length ``f`` px, principal point at the image centre."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    w, h = size
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    return Camera(name=name, K=K, R=R, t=-R @ eye, width=w, height=h)


def ring_rig(n: int = 4, radius: float = 12.0, height: float = 5.0, phase: float = 0.3,
             squash: float = 1.0, size: tuple[int, int] = (1280, 960)) -> Rig:
    """``n`` cameras ``cam0``.. evenly spaced in angle on a ring at ``height`` m, the first at
    angle ``phase`` rad, all looking at (0, 0, 1): a circle of ``radius`` m, or with ``squash``
    < 1 an ellipse whose y semi-axis is ``squash * radius`` (a court's shape); images ``size``."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + phase
    return Rig([look_at(f"cam{i}", (radius * np.cos(a), squash * radius * np.sin(a), height),
                        size=size) for i, a in enumerate(ang)])


#: ring_rig keywords of a court-shaped ring (an ellipse, HD images): the geometry the
#: triangulation, uncertainty and joint filter tests set their bounds on
COURT_RING = dict(phase=0.0, squash=0.8, size=(1920, 1080))


def project_detections(cam: Camera, joints: np.ndarray, verts: np.ndarray | None = None, *,
                       centres: np.ndarray | None = None, kpts3d_world: np.ndarray | None = None,
                       scores: float | Sequence[float] | np.ndarray = 0.95, stamp_ns: int = 0,
                       noise_px: float = 0.0, rng: np.random.Generator | None = None
                       ) -> FrameDetections:
    """Camera ``cam``'s detections of P people, in the given order.

    joints (P,J,3) world m -> kpts2d (P,J,2) rectified px, plus N(0, ``noise_px``) noise from
    ``rng``; kpts3d (P,J,3) camera-frame m of ``kpts3d_world`` (default: the joints); verts
    (P,V,3) world m -> verts2d (P,V,2) float32, (P,0,2) without. bbox: centred on the projected
    ``centres`` (P,3) world m with half the projected vertices' extent (an exact detector's box
    around a body), else the extent of the (noisy) keypoints.
    """
    joints = np.asarray(joints, float)
    P, J = joints.shape[:2]
    kp = cam.project_rectified(joints)
    if noise_px:
        kp = kp + (rng or np.random.default_rng()).normal(scale=noise_px, size=kp.shape)
    uv = (cam.project_rectified(np.asarray(verts, float)) if verts is not None
          else np.zeros((P, 0, 2)))
    if centres is not None:
        half = 0.5 * (uv.max(1) - uv.min(1))
        c = cam.project_rectified(np.asarray(centres, float))
        bboxes = np.concatenate([c - half, c + half], 1)
    else:
        bboxes = np.concatenate([kp.min(1), kp.max(1)], 1)
    kp3d = cam.world_to_camera(joints if kpts3d_world is None else np.asarray(kpts3d_world, float))
    sc = np.broadcast_to(np.asarray(scores, float), (P,)).copy()
    return FrameDetections(cam.name, stamp_ns, bboxes, sc, kp, kp3d, uv.astype(np.float32))


def project_frames(rig: Rig, joints: np.ndarray, verts: np.ndarray | None = None,
                   rng: np.random.Generator | None = None, **kw) -> dict[str, FrameDetections]:
    """Every camera of ``rig`` sees every person (detection index = person index):
    :func:`project_detections` per camera, in rig order, drawing noise from one ``rng``."""
    return {cam.name: project_detections(cam, joints, verts, rng=rng, **kw) for cam in rig}
