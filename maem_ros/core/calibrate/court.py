"""Court points: known landmarks (court coordinates, m) and where they are in the images.

File format (YAML; doc/calibration.md, example config/court_points_fiba.yaml)::

    landmarks:                 # name: [x, y, z] court coordinates, metres
      centre: [0.0, 0.0, 0.0]
      corner_a: [-14.0, -7.5, 0.0]
    pixels:                    # camera name: {landmark name: [u, v]} RAW image px
      cam0: {centre: [812.5, 402.0], corner_a: [120.0, 611.5]}

A landmark seen in two or more views is triangulated; one seen in a single view and lying on
the floor (z = 0) is that view's ray through the people's floor. Three or more non-collinear
landmarks fix the similarity (Umeyama); two fix scale, origin and heading on the people's floor.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..geometry.camera import Rig
from ..geometry.procrustes import procrustes_align
from .tracks import projection_matrices, triangulate
from .world import Similarity


@dataclass
class CourtPoints:
    """Landmarks (L,3) court m with ``names``, and per camera name {landmark index: raw px}."""

    names: list[str]
    court: np.ndarray
    pixels: dict[str, dict[int, np.ndarray]]


def read_court_points(path: str | Path) -> CourtPoints:
    """Parse a court-points YAML; ValueError naming the file and what is wrong."""
    where = f"court points {str(path)!r}"
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as e:
        raise ValueError(f"{where}: cannot read ({e.strerror})") from None
    except yaml.YAMLError as e:
        raise ValueError(f"{where}: not YAML ({str(e).splitlines()[0]})") from None
    if (
        not isinstance(data, dict)
        or not isinstance(data.get("landmarks"), dict)
        or not isinstance(data.get("pixels"), dict)
    ):
        raise ValueError(
            f"{where}: needs a 'landmarks' mapping (name: [x, y, z] m) and a "
            f"'pixels' mapping (camera: {{name: [u, v]}})"
        )
    names = [str(n) for n in data["landmarks"]]
    try:
        court = np.array([np.asarray(data["landmarks"][n], float).reshape(3) for n in data["landmarks"]])
    except (TypeError, ValueError):
        raise ValueError(f"{where}: landmarks: each needs [x, y, z] in metres") from None
    index = {n: i for i, n in enumerate(names)}
    pixels: dict[str, dict[int, np.ndarray]] = {}
    for cam, marks in data["pixels"].items():
        if marks is None:
            continue
        if not isinstance(marks, dict):
            raise ValueError(f"{where}: pixels of camera {cam!r}: expected {{landmark: [u, v]}}")
        for name, uv in marks.items():
            if str(name) not in index:
                raise ValueError(f"{where}: pixels of camera {cam!r}: unknown landmark {name!r}")
            try:
                pixels.setdefault(str(cam), {})[index[str(name)]] = np.asarray(uv, float).reshape(2)
            except (TypeError, ValueError):
                raise ValueError(
                    f"{where}: pixels of camera {cam!r} landmark {name!r}: expected [u, v]"
                ) from None
    if not np.all(np.isfinite(court)):
        raise ValueError(f"{where}: landmarks: NaN or inf")
    return CourtPoints(names, court, pixels)


def locate_landmarks(points: CourtPoints, rig: Rig) -> np.ndarray:
    """(L,3) landmark positions in the rig's frame (NaN where not located): triangulated from
    two or more views, or a floor landmark's single-view ray through z = 0."""
    L = len(points.names)
    cams = [c for c in rig.names if c in points.pixels]
    uv = np.full((len(cams), L, 2), np.nan)
    for k, name in enumerate(cams):
        cam = rig[name]
        for i, px in points.pixels[name].items():
            uv[k, i] = cam.undistort_points(px[None])[0]
    P = projection_matrices(
        np.stack([rig[n].K_rect for n in cams]),
        np.stack([rig[n].R for n in cams]),
        np.stack([rig[n].t for n in cams]),
    )
    X = triangulate(P, uv) if len(cams) >= 2 else np.full((L, 3), np.nan)
    for i in range(L):
        seen = np.flatnonzero(np.all(np.isfinite(uv[:, i]), axis=1))
        if np.isfinite(X[i]).all() or seen.size != 1 or abs(points.court[i, 2]) > 1e-6:
            continue
        cam = rig[cams[seen[0]]]
        ray = cam.R.T @ np.linalg.solve(cam.K_rect, np.append(uv[seen[0], i], 1.0))
        c = cam.center
        if abs(ray[2]) > 1e-9 and -c[2] / ray[2] > 0:
            X[i] = c + (-c[2] / ray[2]) * ray
    return X


def court_similarity(points: CourtPoints, rig: Rig) -> Similarity:
    """The similarity from the rig's frame (z up on the people's floor) to court coordinates;
    ValueError when fewer than two landmarks are located. A closed-form start (landmarks
    located in the rig's frame, single-view ones on the people's floor) is refined by
    minimising the landmarks' reprojection error in every view that marks them (7 unknowns,
    scipy least_squares), which no longer depends on the people's floor."""
    sim = _fit(locate_landmarks(points, rig), points)
    cams, idx, uv = [], [], []
    for name, marks in points.pixels.items():
        if name in rig:
            for i, px in marks.items():
                cams.append(rig.index(name))
                idx.append(i)
                uv.append(rig[name].undistort_points(px[None])[0])
    if len(idx) < 4:
        return sim
    cam_arr, idx_arr, uv_arr = np.array(cams), np.array(idx), np.array(uv)
    P = projection_matrices(
        np.stack([c.K_rect for c in rig]), np.stack([c.R for c in rig]), np.stack([c.t for c in rig])
    )

    def residuals(x: np.ndarray) -> np.ndarray:
        Q = Rotation.from_rotvec(x[:3]).as_matrix()
        X = (points.court[idx_arr] - x[4:]) @ Q / np.exp(x[3])  # court -> rig frame
        h = np.einsum("nij,nj->ni", P[cam_arr][:, :, :3], X) + P[cam_arr][:, :, 3]
        return (h[:, :2] / h[:, 2:] - uv_arr).ravel()

    x0 = np.concatenate([Rotation.from_matrix(sim.Q).as_rotvec(), [np.log(sim.s)], sim.d])
    sol = least_squares(residuals, x0, method="lm")
    return Similarity(float(np.exp(sol.x[3])), Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[4:])


def _fit(X: np.ndarray, points: CourtPoints) -> Similarity:
    ok = np.all(np.isfinite(X), axis=1)
    if ok.sum() < 2:
        raise ValueError(
            f"court points: only {int(ok.sum())} landmark(s) located (each needs "
            f"two views, or one view and z = 0); need at least 2"
        )
    A, B = X[ok], points.court[ok]
    spread = np.linalg.svd(B - B.mean(0), compute_uv=False)
    if ok.sum() >= 3 and spread[1] > 1e-3 * spread[0]:
        _, s, Q, d = procrustes_align(A[None], B[None])
        return Similarity(float(s[0]), Q[0], d[0])
    # two landmarks (or collinear ones): keep the floor's z, fit heading, scale and origin
    a2, b2 = A[:, :2] - A[:, :2].mean(0), B[:, :2] - B[:, :2].mean(0)
    k = int(np.argmax(np.linalg.norm(b2, axis=1)))
    scale = float(np.linalg.norm(b2[k]) / np.linalg.norm(a2[k]))
    ang = np.arctan2(b2[k, 1], b2[k, 0]) - np.arctan2(a2[k, 1], a2[k, 0])
    Q = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    d = B.mean(0) - scale * Q @ A.mean(0)
    return Similarity(scale, Q, d)
