"""Rendered calibration-board sequences: a ChArUco or checkerboard moved through the volume and
imaged by every camera of a rig through its lens model, with the ground truth.

Rendering is an exact per-pixel inverse mapping: every (2x supersampled) raw pixel is undistorted
by the camera's own model (Camera.undistort_points, iterated to 1e-9) into a viewing ray, the
ray is cut with the board plane, and the board texture (OpenCV's
``CharucoBoard.generateImage``, or a checkerboard) is sampled there with ``cv2.remap``; the
image is then area-averaged to the camera's size, slightly blurred (a lens' point spread) and
given sensor noise. The board's back (seen from behind) is plain grey.

A sequence (:func:`board_poses`): board poses (board -> world, OpenCV board frame, see
core.calibrate.board) at random points of the cameras' common volume, facing the cameras
that see the point with a random tilt and in-plane turn; with ``per_camera`` every camera gets
its own poses in front of it instead (photographed one camera at a time, as for intrinsics).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from maem_ros.core.calibrate.board import BoardSpec
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.sim.view import distort_xy

#: texture pixels per board square; supersampling of the rendered image
TEXTURE_SQUARE_PX = 96
SUPERSAMPLE = 2
#: white border around the squares, in squares (real boards have one; detectors need it)
BORDER_SQUARES = 0.6
_BACK_GREY, _BACKGROUND = 110, 150
#: raw px between exactly undistorted pixels; largest error of the interpolated lens map, px
#: (far below the detectors' corner noise, ~0.05 px; OpenCV's iterative inverse alone is
#: 3e-3 px off at an extreme corner of sportcenter6's camera_4, k1 -0.33)
_GRID_PX, _MAX_MAP_ERROR_PX = 2.0, 5e-3


def board_texture(spec: BoardSpec) -> tuple[np.ndarray, float]:
    """(H,W) uint8 image of the board face with its white border, and its px per metre."""
    sx, sy = spec.squares
    px = TEXTURE_SQUARE_PX
    if spec.kind == "charuco":
        face = spec.charuco_board().generateImage((sx * px, sy * px), marginSize=0)
    else:  # top-left square black, as OpenCV's boards
        ij = np.add.outer(np.arange(sy * px) // px, np.arange(sx * px) // px)
        face = np.where(ij % 2 == 0, 0, 255).astype(np.uint8)
    border = int(round(BORDER_SQUARES * px))
    return cv2.copyMakeBorder(
        face, border, border, border, border, cv2.BORDER_CONSTANT, value=255
    ), px / spec.square


def _rays(cam: Camera) -> np.ndarray:
    """(H*s, W*s, 3) camera-frame rays (z = 1) of the supersampled raw pixel centres."""
    s = SUPERSAMPLE
    u = (np.arange(cam.width * s) + 0.5) / s - 0.5
    v = (np.arange(cam.height * s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    x, y = _undistort_dense(cam, uu, vv)
    return np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float32)


def _undistort_dense(cam: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole x, y of raw px u, v (same shape, a regular grid): Camera.undistort_points
    (OpenCV, iterated to 1e-9) on a grid of every ``_GRID_PX`` px, bilinearly interpolated (the
    lens map is smooth: the error is checked on a sample through the camera's own forward model,
    sim.view.distort_xy, and must stay below ``_MAX_MAP_ERROR_PX``)."""
    du, dv = u[0, 1] - u[0, 0], v[1, 0] - v[0, 0]
    gu = np.arange(u[0, 0], u[0, -1] + _GRID_PX, _GRID_PX)
    gv = np.arange(v[0, 0], v[-1, 0] + _GRID_PX, _GRID_PX)
    rect = cam.undistort_points(np.stack(np.meshgrid(gu, gv), axis=-1))
    grid = (rect - cam.K_rect[:2, 2]) @ np.linalg.inv(cam.K_rect[:2, :2]).T  # (gv, gu, 2)
    fi = (np.arange(u.shape[1]) * du) / _GRID_PX  # fractional grid columns
    fj = (np.arange(v.shape[0]) * dv) / _GRID_PX
    i0 = np.minimum(fi.astype(np.int64), gu.size - 2)
    j0 = np.minimum(fj.astype(np.int64), gv.size - 2)
    wi = (fi - i0)[None, :, None]
    wj = (fj - j0)[:, None, None]
    top = grid[j0][:, i0] * (1 - wi) + grid[j0][:, i0 + 1] * wi
    bottom = grid[j0 + 1][:, i0] * (1 - wi) + grid[j0 + 1][:, i0 + 1] * wi
    xy = top * (1 - wj) + bottom * wj
    sample = (slice(None, None, 7), slice(None, None, 5))
    pu, pv = distort_xy(cam, xy[sample][..., 0], xy[sample][..., 1])
    worst = float(np.nanmax(np.hypot(pu - u[sample], pv - v[sample])))
    if not worst < _MAX_MAP_ERROR_PX:
        raise ValueError(
            f"camera {cam.name!r}: lens map not smooth enough to render a board "
            f"(interpolation error {worst:.2g} px)"
        )
    return xy[..., 0], xy[..., 1]


#: rays per lens and image size, the most recently used few (each is tens of MB)
_RAYS: OrderedDict[tuple, np.ndarray] = OrderedDict()
_RAYS_KEPT = 8


def _camera_rays(cam: Camera) -> np.ndarray:
    """The camera's supersampled pixel rays, computed once per lens and image size."""
    key = (
        cam.width,
        cam.height,
        cam.distortion_model,
        tuple(cam.K.ravel()),
        tuple(cam.K_rect.ravel()),
        tuple(cam.D),
    )
    if key not in _RAYS:
        _RAYS[key] = _rays(cam)
        while len(_RAYS) > _RAYS_KEPT:
            _RAYS.popitem(last=False)
    _RAYS.move_to_end(key)
    return _RAYS[key]


def render_board(
    cam: Camera,
    spec: BoardSpec,
    R_wb: np.ndarray,
    t_wb: np.ndarray,
    rng: np.random.Generator,
    texture: tuple[np.ndarray, float] | None = None,
    noise: float = 2.0,
) -> np.ndarray:
    """(H,W) uint8 raw image of the board at pose (R_wb, t_wb) (board -> world, m) seen by ``cam``."""
    tex, ppm = texture or board_texture(spec)
    rays = _camera_rays(cam)
    R_cb = cam.R @ R_wb  # board -> camera
    o = cam.R @ t_wb + cam.t
    n = R_cb[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(n @ o) / (rays @ n.astype(np.float32))
    in_front = np.isfinite(lam) & (lam > 0)
    lam[~in_front] = 0.0  # rays parallel to or away from the plane: no hit (masked below)
    hit = rays * lam[..., None] - o.astype(np.float32)
    border = BORDER_SQUARES * spec.square
    x = (hit @ R_cb[:, 0].astype(np.float32) + border) * ppm - 0.5
    y = (hit @ R_cb[:, 1].astype(np.float32) + border) * ppm - 0.5
    x[~in_front] = -1e6
    y[~in_front] = -1e6
    sampled = cv2.remap(tex, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = (
        cv2.remap(
            np.full(tex.shape, 255, np.uint8),
            x,
            y,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        ).astype(np.float32)
        / 255
    )
    face = sampled.astype(np.float32) if float(n @ o) > 0 else np.full(x.shape, _BACK_GREY, np.float32)
    background = _BACKGROUND + 25 * np.sin(np.linspace(0, 3, x.shape[1]))[None, :].astype(np.float32)
    img: np.ndarray = inside * face + (1 - inside) * background
    img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.5)
    img += rng.normal(0.0, noise, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def board_corners_world(spec: BoardSpec, R_wb: np.ndarray, t_wb: np.ndarray) -> np.ndarray:
    """(N,3) world m of the inner corners at pose (R_wb, t_wb)."""
    return spec.corners() @ R_wb.T + t_wb


def _visible(cam: Camera, X: np.ndarray, margin: float) -> bool:
    uv = cam.project(X)
    return bool(
        np.all(np.isfinite(uv))
        and np.all(uv >= margin)
        and np.all(uv[:, 0] <= cam.width - 1 - margin)
        and np.all(uv[:, 1] <= cam.height - 1 - margin)
    )


def _facing(
    spec: BoardSpec, centre: np.ndarray, towards: np.ndarray, rng: np.random.Generator, max_tilt_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Board pose centred at ``centre`` whose pattern faces ``towards`` (unit, world), tilted
    by up to ``max_tilt_deg`` and turned in plane at random."""
    z = -towards / np.linalg.norm(towards)  # board z points away from the viewers
    axis = np.cross(z, rng.normal(size=3))
    tilt = Rotation.from_rotvec(
        axis / max(np.linalg.norm(axis), 1e-9) * np.radians(rng.uniform(0, max_tilt_deg))
    )
    z = tilt.apply(z)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    spin = rng.uniform(-np.pi, np.pi)
    x, y = np.cos(spin) * x + np.sin(spin) * y, -np.sin(spin) * x + np.cos(spin) * y
    R = np.column_stack([x, y, z])
    half = np.array([(spec.cols + 1) * spec.square / 2, (spec.rows + 1) * spec.square / 2, 0.0])
    return R, centre - R @ half


def _common_centre(rig: Rig) -> np.ndarray:
    """Least-squares point nearest every camera's optical axis (world m); for one camera, the
    point 3 m along its axis."""
    if len(rig) == 1:
        return rig[0].center + 3.0 * rig[0].R[2]
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in rig:
        d = cam.R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    return np.linalg.solve(A, b)


@dataclass
class BoardPoses:
    """Board -> world poses R (F,3,3), t (F,3); ``camera`` (F,) the camera a per-camera pose
    is meant for (-1: shared by every camera that sees it)."""

    R: np.ndarray
    t: np.ndarray
    camera: np.ndarray


def board_poses(
    rig: Rig,
    spec: BoardSpec,
    frames: int,
    seed: int = 0,
    per_camera: bool = False,
    min_cameras: int = 2,
    max_tilt_deg: float = 40.0,
) -> BoardPoses:
    """Random board poses (module docstring): shared ones seen whole by ``min_cameras``+
    cameras, or with ``per_camera`` ``frames`` poses per camera seen whole by that camera."""
    rng = np.random.default_rng([int(seed), 5151])
    centre = _common_centre(rig)
    radius = 0.35 * np.median([np.linalg.norm(c.center - centre) for c in rig])
    Rs, ts, owners = [], [], []
    targets = [(c, frames) for c in range(len(rig))] if per_camera else [(-1, frames)]
    for owner, count in targets:
        got, tries = 0, 0
        while got < count:
            tries += 1
            if tries > 400 * count:
                raise ValueError(
                    f"board poses: could not place {count} boards of {spec} in view "
                    f"({'camera ' + rig[owner].name if owner >= 0 else 'the common volume'})"
                )
            if owner >= 0:
                cam = rig[owner]
                # close-ups all over the image, as for an intrinsic calibration
                depth = rng.uniform(0.35, 0.8) * np.linalg.norm(cam.center - centre)
                ray = np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.35, 0.35), 1.0])
                p = cam.R.T @ (ray * depth - cam.t)
                towards, viewers = cam.center - p, [owner]
            else:
                p = centre + rng.uniform(-1, 1, 3) * radius * np.array([1.0, 1.0, 0.6])
                viewers = [c for c, cam in enumerate(rig) if _visible(cam, p[None], 60)]
                if len(viewers) < min_cameras:
                    continue
                # face one viewer and its nearest other viewer (their bisector): both see the
                # pattern well, the board is not edge-on to either
                # the cameras take turns to be faced, so every camera shares boards
                turn = got % len(rig)
                first = turn if turn in viewers else int(rng.choice(viewers))
                dirs = {c: (rig[c].center - p) / np.linalg.norm(rig[c].center - p) for c in viewers}
                second = max(
                    (c for c in viewers if c != first), key=lambda c: dirs[c] @ dirs[first], default=first
                )
                towards = dirs[first] + dirs[second]
            R, t = _facing(spec, p, towards, rng, max_tilt_deg)
            X = board_corners_world(spec, R, t)
            seen = [c for c in viewers if _visible(rig[c], X, 8) and _faces(rig[c], R, t)]
            if len(seen) >= (1 if owner >= 0 else min_cameras):
                Rs.append(R)
                ts.append(t)
                owners.append(owner)
                got += 1
    return BoardPoses(np.stack(Rs), np.stack(ts), np.array(owners, dtype=np.int64))


def _faces(cam: Camera, R_wb: np.ndarray, t_wb: np.ndarray, min_cos: float = 0.4) -> bool:
    """The pattern faces the camera at more than acos(min_cos) from edge-on."""
    view = cam.center - (t_wb + R_wb @ np.array([0.1, 0.1, 0.0]))
    return bool(float(-R_wb[:, 2] @ view) / np.linalg.norm(view) > min_cos)


def write_board_sequence(
    out: str | Path, rig: Rig, spec: BoardSpec, poses: BoardPoses, seed: int = 0, intrinsics_only: bool = True
) -> Path:
    """Render ``poses`` into every camera and write ``out``::

    images/<camera>/<frame:06d>.png   raw grayscale images (per-camera poses: only the
                                      owner camera's frames)
    gt_rig.yaml                       the true rig
    board.npz                         spec (str), R (F,3,3), t (F,3) board -> world, camera (F,)
    cameras/<camera>.json             MAEM camera JSON (intrinsics only by default)
    """
    out = Path(out)
    rng = np.random.default_rng([int(seed), 5152])
    texture = board_texture(spec)
    for c, cam in enumerate(rig):
        folder = out / "images" / cam.name
        folder.mkdir(parents=True, exist_ok=True)
        for f in range(len(poses.R)):
            if poses.camera[f] not in (-1, c):
                continue
            img = render_board(cam, spec, poses.R[f], poses.t[f], rng, texture)
            if not cv2.imwrite(str(folder / f"{f:06d}.png"), img):
                raise ValueError(f"image {str(folder / f'{f:06d}.png')!r}: cv2.imwrite failed")
    rig.to_yaml(out / "gt_rig.yaml")
    rig.to_json_folder(out / "cameras", extrinsics=not intrinsics_only)
    np.savez(out / "board.npz", spec=str(spec), R=poses.R, t=poses.t, camera=poses.camera)
    return out
