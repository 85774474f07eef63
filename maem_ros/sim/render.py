"""Raw (distorted) camera images of the court and the people on it.

The background (floor, stands, court lines) is computed once per camera: a coarse grid of raw
pixels is undistorted, cast onto the floor plane z = 0 and upsampled, so floor colour, wood
stripes and the painted lanes follow the lens exactly; lines are world polylines projected with
the lens model. People are drawn far-to-near per body part as filled convex hulls of their
projected mesh vertices (team colours, per-person skin tone), with floor shadows.
"""

from __future__ import annotations

import cv2
import numpy as np

from maem_ros.core.geometry.camera import Camera

from .body import PART_CLASS, PART_NAMES, BodyModel
from .rigs import BASKETS, COURT_LENGTH, COURT_WIDTH
from .view import project_raw

_HULL_SAMPLES = 40
# BGR colours
_JERSEY = {0: (40, 40, 190), 1: (185, 110, 25), 2: (35, 35, 35)}
_SHORTS = {0: (30, 30, 140), 1: (140, 80, 20), 2: (20, 20, 20)}
_SHOES = (235, 235, 235)
_FLOOR_IN, _FLOOR_OUT, _PAINT, _LINE = (95, 150, 205), (60, 95, 140), (60, 80, 150), (245, 245, 245)


def court_polylines(step: float = 0.05) -> list[np.ndarray]:
    """World polylines (M,3) of the court markings (FIBA layout), metres."""
    hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
    lines = []

    def seg(a, b):
        n = max(2, int(np.hypot(b[0] - a[0], b[1] - a[1]) / step))
        t = np.linspace(0, 1, n)[:, None]
        return np.column_stack([(1 - t) * a[0] + t * b[0], (1 - t) * a[1] + t * b[1], np.zeros(n)])

    def arc(c, r, a0, a1):
        n = max(8, int(abs(a1 - a0) * r / step))
        a = np.linspace(a0, a1, n)
        return np.column_stack([c[0] + r * np.cos(a), c[1] + r * np.sin(a), np.zeros(n)])

    lines.append(
        np.concatenate(
            [
                seg((-hx, -hy), (hx, -hy)),
                seg((hx, -hy), (hx, hy)),
                seg((hx, hy), (-hx, hy)),
                seg((-hx, hy), (-hx, -hy)),
            ]
        )
    )
    lines.append(seg((0, -hy), (0, hy)))
    lines.append(arc((0, 0), 1.8, 0, 2 * np.pi))
    for sgn in (-1.0, 1.0):
        bx = sgn * (hx - 1.575)
        ft = sgn * (hx - 5.8)  # free-throw line
        lines.append(
            np.concatenate(
                [
                    seg((sgn * hx, -2.45), (ft, -2.45)),
                    seg((ft, -2.45), (ft, 2.45)),
                    seg((ft, 2.45), (sgn * hx, 2.45)),
                ]
            )
        )
        inward = np.pi if sgn > 0 else 0.0  # direction from this basket to the court centre
        lines.append(arc((ft, 0), 1.8, inward - np.pi / 2, inward + np.pi / 2))
        # three-point line: straight parts 0.9 m in from the sidelines, then the 6.75 m arc
        a = np.arcsin((hy - 0.9) / 6.75)
        xa = bx - sgn * 6.75 * np.cos(a)
        lines.append(
            np.concatenate(
                [
                    seg((sgn * hx, -(hy - 0.9)), (xa, -(hy - 0.9))),
                    arc((bx, 0), 6.75, inward + sgn * a, inward - sgn * a),
                    seg((xa, hy - 0.9), (sgn * hx, hy - 0.9)),
                ]
            )
        )
        lines.append(arc((bx, 0), 1.25, inward - np.pi / 2, inward + np.pi / 2))
    return lines


class Renderer:
    """Renders raw images; caches one background per camera."""

    def __init__(self, body: BodyModel, team: np.ndarray, seed: int = 0):
        self.body = body
        self.team = np.asarray(team)
        rng = np.random.default_rng([int(seed), 77])
        tone = rng.uniform(0.0, 1.0, len(self.team))
        light, dark = np.array([150, 180, 225.0]), np.array([45, 70, 110.0])
        self.skin = light[None] * (1 - tone[:, None]) + dark[None] * tone[:, None]
        self.sample = body.part_vertex_sample(_HULL_SAMPLES)
        self.sample_part = body.part_of[self.sample]
        self._backgrounds: dict[str, np.ndarray] = {}

    def background(self, cam: Camera) -> np.ndarray:
        key = cam.name + repr(cam.K.tolist()) + repr(cam.t.tolist())
        if key not in self._backgrounds:
            self._backgrounds[key] = _background(cam)
        return self._backgrounds[key]

    def render(self, cam: Camera, verts: np.ndarray, points: np.ndarray) -> np.ndarray:
        """verts (P,V,3) world m; points (P,>=70,3) skeleton points (for shadows) -> BGR uint8 raw image."""
        img = self.background(cam).copy()
        P = verts.shape[0]
        if P == 0:
            return img
        _shadows(img, cam, points)
        sv = verts[:, self.sample]  # (P,S,3)
        uv = project_raw(cam, sv)
        depth = cam.world_to_camera(sv)[..., 2]
        K = len(PART_NAMES)
        onehot = self.sample_part[None, :] == np.arange(K)[:, None]  # (K,S)
        part_depth = (depth[:, None, :] * onehot[None]).sum(-1) / onehot.sum(-1)[None]  # (P,K)
        order = np.argsort(-part_depth, axis=None)
        light = 0.75 + 0.25 * np.clip(1.0 - (depth - depth.min()) / max(np.ptp(depth), 1e-6), 0, 1)
        for flat in order:
            p, k = divmod(int(flat), K)
            pts = uv[p, onehot[k]]
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            if len(pts) < 3 or part_depth[p, k] <= 0:
                continue
            hull = cv2.convexHull(np.round(pts).astype(np.int32))
            colour = np.asarray(self._colour(p, PART_CLASS[PART_NAMES[k]])) * light[p].mean()
            cv2.fillConvexPoly(img, hull, tuple(float(c) for c in colour), lineType=cv2.LINE_AA)
            cv2.polylines(img, [hull], True, tuple(float(c) * 0.55 for c in colour), 1, cv2.LINE_AA)
        return img

    def _colour(self, person: int, cls: int) -> tuple[float, float, float]:
        team = int(self.team[person])
        if cls == 0:
            return tuple(self.skin[person])
        if cls == 1:
            return _JERSEY.get(team, _JERSEY[2])
        if cls == 2:
            return _SHORTS.get(team, _SHORTS[2])
        return _SHOES


def _shadows(img: np.ndarray, cam: Camera, points: np.ndarray) -> None:
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    centre = points[:, :70, :2].mean(axis=1)  # (P,2)
    ring = np.concatenate(
        [
            centre[:, None, :] + 0.45 * np.stack([np.cos(a), 0.7 * np.sin(a)], 1)[None],
            np.zeros((len(centre), len(a), 1)),
        ],
        axis=2,
    )
    uv = project_raw(cam, ring)
    overlay = img.copy()
    for poly in uv:
        if np.all(np.isfinite(poly)):
            cv2.fillPoly(overlay, [np.round(poly).astype(np.int32)], (0, 0, 0), cv2.LINE_AA)
    cv2.addWeighted(overlay, 0.35, img, 0.65, 0, dst=img)


def _background(cam: Camera, step: int = 8) -> np.ndarray:
    """Floor, stands, painted areas and lines of the court as seen in the raw image."""
    w, h = cam.width, cam.height
    gx, gy = np.meshgrid(
        np.arange(0, w + step, step, dtype=np.float64), np.arange(0, h + step, step, dtype=np.float64)
    )
    rect = cam.undistort_points(np.stack([gx, gy], -1).reshape(-1, 2))
    rays = np.column_stack([rect, np.ones(len(rect))]) @ np.linalg.inv(cam.K_rect).T @ cam.R  # world dirs
    c = cam.center
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -c[2] / rays[:, 2]
    hit = (lam > 0) & (lam < 200)
    xy = c[:2] + lam[:, None] * rays[:, :2]
    xy = np.where(hit[:, None], xy, 1e3)
    # coarse grid to full resolution (cv2.resize maps grid sample i to pixel i * step)
    fx = cv2.resize(
        xy[:, 0].reshape(gx.shape).astype(np.float32), None, fx=step, fy=step, interpolation=cv2.INTER_LINEAR
    )[:h, :w]
    fy = cv2.resize(
        xy[:, 1].reshape(gx.shape).astype(np.float32), None, fx=step, fy=step, interpolation=cv2.INTER_LINEAR
    )[:h, :w]
    elev = cv2.resize(
        rays[:, 2].reshape(gx.shape).astype(np.float32),
        None,
        fx=step,
        fy=step,
        interpolation=cv2.INTER_LINEAR,
    )[:h, :w]
    hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
    floor = (np.abs(fx) < 45.0) & (np.abs(fy) < 35.0) & (elev < 0)  # the walls stop the floor
    court = floor & (np.abs(fx) <= hx) & (np.abs(fy) <= hy)
    apron = floor & (np.abs(fx) <= hx + 4) & (np.abs(fy) <= hy + 3.5)
    lane = court & (np.abs(fy) <= 2.45) & (np.abs(fx) >= hx - 5.8)
    img = np.empty((h, w, 3), np.float32)
    stands = (
        np.array([70, 60, 55], np.float32) + 25 * np.sin(np.arange(h, dtype=np.float32) / 9.0)[:, None, None]
    )
    img[:] = stands
    img[floor] = _FLOOR_OUT
    img[apron] = np.array(_FLOOR_OUT) * 1.15
    img[court] = _FLOOR_IN
    img[lane] = _PAINT
    stripe = 1.0 + 0.035 * np.sin(fx * 2 * np.pi / 0.9) * apron  # parquet planks
    img *= stripe[..., None]
    out = np.clip(img, 0, 255).astype(np.uint8)
    thick = max(2, int(round(min(w, h) / 400)))
    for line in court_polylines():
        uv = project_raw(cam, line)
        for run in _finite_runs(uv):
            cv2.polylines(out, [np.round(run).astype(np.int32)], False, _LINE, thick, cv2.LINE_AA)
    for b in BASKETS:  # basket stanchion shadow + rim for orientation
        uv = project_raw(
            cam, np.array([[b[0] + np.sign(b[0]) * 1.2, 0.0, 0.0], [b[0] + np.sign(b[0]) * 1.2, 0.0, 3.3]])
        )
        if np.all(np.isfinite(uv)):
            cv2.line(
                out,
                tuple(np.round(uv[0]).astype(int)),
                tuple(np.round(uv[1]).astype(int)),
                (90, 90, 90),
                thick * 3,
                cv2.LINE_AA,
            )
        a = np.linspace(0, 2 * np.pi, 24)
        rim = project_raw(
            cam, np.column_stack([b[0] + 0.23 * np.cos(a), 0.23 * np.sin(a), np.full(24, b[2])])
        )
        if np.all(np.isfinite(rim)):
            cv2.polylines(out, [np.round(rim).astype(np.int32)], True, (20, 80, 230), thick, cv2.LINE_AA)
    noise = np.random.default_rng(len(cam.name) * 131 + w).integers(-6, 7, out.shape, dtype=np.int16)
    return np.clip(out.astype(np.int16) + noise, 0, 255).astype(np.uint8)


def _finite_runs(uv: np.ndarray) -> list[np.ndarray]:
    ok = np.all(np.isfinite(uv), axis=1) & (np.abs(uv) < 1e5).all(axis=1)
    runs, start = [], None
    for i, good in enumerate(np.append(ok, False)):
        if good and start is None:
            start = i
        elif not good and start is not None:
            if i - start >= 2:
                runs.append(uv[start:i])
            start = None
    return runs
