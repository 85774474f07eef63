"""Detection-noise model of a monocular mesh-recovery frontend (SAM 3D Body-like).

For one camera and frame, every person is first tested for visibility: a fixed sample of its
surface vertices is projected; a sample counts as visible when it is inside the raw image and
not covered by a part box (per body part bbox) of a person nearer to the camera. A person is
missed when its visible fraction is below ``min_visible`` (mostly occluded or outside the
image) or when it is smaller than ``min_height_px`` (too far away), plus a small random miss rate
that grows with occlusion.

A detected person's estimate is the body model re-posed with noisy joint angles (``angle_sigma``
rad on every angle, ``heading_sigma`` on the body yaw, ``shape_sigma`` relative error on height and
width), re-centred on the true keypoint centroid (the estimator fits the image), then scaled
about the camera centre by (1 + e), e ~ N(0, ``depth_sigma``): the root depth error along the
viewing ray, invisible in 2D as for a real monocular estimate. 3D keypoints get extra iid jitter
``kpt3d_sigma`` m; 2D keypoints / vertices are the projections of the noisy 3D plus iid jitter
``kpt2d_px`` / ``vert2d_px`` (x (1 + 2 * occluded fraction)). Boxes come from the true silhouette
(raw px, clipped to the image: truncated at borders) plus ``bbox_px`` edge jitter.

Scores: players N(0.95, 0.025), bystanders N(0.84, 0.07), minus 0.15 x occluded fraction and
0.3 x truncated fraction, clipped to [0.05, 0.995]. False positives: Poisson(``fp_rate``) per
image, spectator-like bodies off the court with scores U(0.25, 0.85) (8 % U(0.85, 0.93)).

Presets (angle_sigma rad / depth_sigma / kpt2d_px / min_visible / fp_rate):
none 0 / 0 / 0 / - / 0 (exact: no noise, no misses, no false positives, score 0.95);
easy 0.04 / 0.06 / 0.6 / 0.15 / 0.1; medium 0.075 / 0.12 / 1.0 / 0.25 / 0.3;
hard 0.13 / 0.15 / 2.0 / 0.4 / 0.8.

Measured at medium (sportcenter6, seed 11; tests check the ranges): 3D keypoint PA-MPJPE mean
52 mm (range 40-60); median |root depth error| 8 % of the distance (5-15 %); median 2D keypoint
error 2.7 px, vertex error 2.1 px (1-6 px); misses 1 % (sportcenter6) and 7 % (humanm3_4, whose
person-height cameras see more occlusion). Easy / hard PA-MPJPE: about 29 / 89 mm.
Everything is deterministic per (seed, camera index, frame).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.camera import Camera
from .body import ANGLE_KEYS, BodyModel, forward_kinematics, gait_angles
from .rigs import COURT_LENGTH, COURT_WIDTH
from .view import distort_points, inside_image, normalised, project_raw

_SAMPLES_PER_PART = 12


@dataclass(frozen=True)
class NoiseParams:
    """One difficulty preset (units: rad, m, px, fractions, detections per image)."""

    exact: bool = False
    angle_sigma: float = 0.075
    heading_sigma: float = 0.05
    shape_sigma: float = 0.03
    kpt3d_sigma: float = 0.012
    depth_sigma: float = 0.12
    kpt2d_px: float = 1.0
    vert2d_px: float = 0.5
    bbox_px: float = 2.0
    min_visible: float = 0.25
    min_height_px: float = 20.0
    miss_rate: float = 0.01
    fp_rate: float = 0.3
    player_score: tuple[float, float] = (0.95, 0.025)
    bystander_score: tuple[float, float] = (0.84, 0.07)


PRESETS: dict[str, NoiseParams] = {
    "none": NoiseParams(exact=True, angle_sigma=0.0, heading_sigma=0.0, shape_sigma=0.0, kpt3d_sigma=0.0,
                        depth_sigma=0.0, kpt2d_px=0.0, vert2d_px=0.0, bbox_px=0.0, min_visible=0.0,
                        miss_rate=0.0, fp_rate=0.0),
    "easy": NoiseParams(angle_sigma=0.04, heading_sigma=0.03, shape_sigma=0.02, kpt3d_sigma=0.008,
                        depth_sigma=0.06, kpt2d_px=0.6, vert2d_px=0.3, bbox_px=1.0, min_visible=0.15, min_height_px=16.0,
                        miss_rate=0.005, fp_rate=0.1),
    "medium": NoiseParams(),
    "hard": NoiseParams(angle_sigma=0.13, heading_sigma=0.09, shape_sigma=0.05, kpt3d_sigma=0.02,
                        depth_sigma=0.15, kpt2d_px=2.0, vert2d_px=1.0, bbox_px=4.0, min_visible=0.4, min_height_px=28.0,
                        miss_rate=0.03, fp_rate=0.8, player_score=(0.93, 0.035), bystander_score=(0.8, 0.08)),
}


def get_preset(difficulty: str) -> NoiseParams:
    try:
        return PRESETS[difficulty]
    except KeyError:
        raise ValueError(f"difficulty: unknown {difficulty!r}, expected one of {list(PRESETS)}") from None


@dataclass
class PersonState:
    """Everything needed to re-pose the persons of one frame: arrays over P."""

    height: np.ndarray
    width: np.ndarray
    root_xy: np.ndarray
    heading: np.ndarray
    angles: dict[str, np.ndarray]
    is_player: np.ndarray


@dataclass
class SimDetections:
    """Simulated detections of one camera/frame (N detections, 70 keypoints, V vertices).

    person (N,) GT person index, -1 = false positive; bbox_raw (N,4) raw px; bbox_rect (N,4)
    rectified px (raw box moved so its centre is the undistorted raw centre); kpts2d/verts2d
    _rect and _raw px; kpts3d (N,70,3) / verts3d (N,V,3) camera frame m; cam_t (N,3) m.
    """

    person: np.ndarray
    scores: np.ndarray
    bbox_raw: np.ndarray
    bbox_rect: np.ndarray
    kpts2d_rect: np.ndarray
    kpts2d_raw: np.ndarray
    verts2d_rect: np.ndarray
    verts2d_raw: np.ndarray
    kpts3d: np.ndarray
    verts3d: np.ndarray
    cam_t: np.ndarray
    visible_fraction: np.ndarray = field(default_factory=lambda: np.zeros(0))


def visibility(camera: Camera, sample_world: np.ndarray, part_of_sample: np.ndarray,
               num_parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Visible and in-image fractions (P,) of persons given their surface samples (P,S,3) world m.

    Occluders are the per-part boxes (rectified px) of persons whose root is nearer the camera.
    """
    P = sample_world.shape[0]
    raw = project_raw(camera, sample_world)
    in_img = inside_image(camera, raw)
    rect = camera.project_rectified(sample_world)
    depth = camera.world_to_camera(sample_world)[..., 2].mean(axis=1)  # (P,)
    boxes = np.full((P, num_parts, 4), np.nan)
    onehot = part_of_sample[None, :, None] == np.arange(num_parts)[None, None, :]  # (1,S,K)
    with np.errstate(invalid="ignore"):
        for c, (fn, col) in enumerate(((np.nanmin, 0), (np.nanmin, 1), (np.nanmax, 0), (np.nanmax, 1))):
            vals = np.where(onehot, rect[..., col][:, :, None], np.nan)  # (P,S,K)
            boxes[..., c] = _nan_reduce(fn, vals)
        u, v = rect[..., 0][:, :, None, None], rect[..., 1][:, :, None, None]  # (P,S,1,1)
        b = boxes[None, None]  # (1,1,P,K,4)
        cover = ((u >= b[..., 0]) & (u <= b[..., 2]) & (v >= b[..., 1]) & (v <= b[..., 3]))  # (P,S,P,K)
    cover = cover.any(axis=3) & (depth[None, :] < depth[:, None])[:, None, :]  # nearer persons only
    occluded = cover.any(axis=2)
    visible = in_img & ~occluded
    return visible.mean(axis=1), in_img.mean(axis=1)


def _nan_reduce(fn, vals: np.ndarray) -> np.ndarray:
    allnan = np.all(np.isnan(vals), axis=1)
    out = fn(np.where(allnan[:, None, :], 0.0, vals), axis=1)
    return np.where(allnan, np.nan, out)


def simulate(camera: Camera, rng: np.random.Generator, params: NoiseParams, body: BodyModel,
             state: PersonState, gt_points: np.ndarray, gt_verts: np.ndarray) -> SimDetections:
    """Detections of one camera: gt_points (P,70+,3) world m (keypoints first), gt_verts (P,V,3)."""
    sample_idx = body.part_vertex_sample(_SAMPLES_PER_PART)
    vis, in_img = visibility(camera, gt_verts[:, sample_idx], body.part_of[sample_idx], len(body.slices))
    beyond_fold = ~np.all(normalised(camera, gt_verts)[1], axis=1)  # lens fold: no consistent raw px
    occ = np.clip(1.0 - vis / np.maximum(in_img, 1e-9), 0.0, 1.0)
    trunc = 1.0 - in_img
    if params.exact:
        detected = (in_img > 0) & ~beyond_fold
    else:
        u = rng.random(len(vis))
        v = camera.project_rectified(gt_verts[:, sample_idx])[..., 1]
        with np.errstate(invalid="ignore"):
            tall = np.nan_to_num(np.nanmax(v, axis=1) - np.nanmin(v, axis=1)) >= params.min_height_px
        detected = (vis >= params.min_visible) & tall & ~beyond_fold & (u >= params.miss_rate * (1 + 4 * occ))
    idx = np.flatnonzero(detected)
    dets = _estimate(camera, rng, params, body, state, idx, gt_points[:, :70], project_raw(camera, gt_verts[idx]), occ[idx])
    dets.person = idx
    dets.visible_fraction = vis[idx]
    dets.scores = _scores(rng, params, state.is_player[idx], occ[idx], trunc[idx])
    if not params.exact:
        fp = _false_positives(camera, rng, params, body)
        if fp is not None:
            dets = _concat(dets, fp)
    order = rng.permutation(len(dets.person))
    return _take(dets, order)


def _estimate(camera, rng, params, body, state, idx, gt_kpts, gt_raw_verts, occ) -> SimDetections:
    n = len(idx)
    sub_angles = {k: state.angles[k][idx] for k in ANGLE_KEYS}
    if params.exact:
        h, w, yaw, ang = state.height[idx], state.width[idx], state.heading[idx], sub_angles
    else:
        h = state.height[idx] * (1 + params.shape_sigma * rng.standard_normal(n))
        w = state.width[idx] * (1 + params.shape_sigma * rng.standard_normal(n))
        yaw = state.heading[idx] + params.heading_sigma * rng.standard_normal(n)
        ang = {k: v + params.angle_sigma * rng.standard_normal(n) for k, v in sub_angles.items()}
    skel = forward_kinematics(h, w, ang, state.root_xy[idx], yaw)
    verts = body.vertices(skel, h, w)
    kp = skel.keypoints
    shift = gt_kpts[idx].mean(axis=1, keepdims=True) - kp.mean(axis=1, keepdims=True)
    kp, verts = kp + shift, verts + shift  # the estimator fits the person's image position
    depth = 1.0 + (0.0 if params.exact else np.clip(params.depth_sigma * rng.standard_normal(n), -0.4, 0.4))
    depth = np.broadcast_to(depth, (n,))[:, None, None]
    kc = camera.world_to_camera(kp)
    vc = camera.world_to_camera(verts)
    jit = 1.0 + 2.0 * occ[:, None, None]
    k2 = camera.project_rectified(kp) + params.kpt2d_px * jit * rng.standard_normal(kp.shape[:2] + (2,))
    v2 = camera.project_rectified(verts)
    if params.vert2d_px > 0:
        v2 = v2 + params.vert2d_px * jit * rng.standard_normal(v2.shape)
    kpts3d = depth * kc
    if params.kpt3d_sigma > 0:
        kpts3d = kpts3d + params.kpt3d_sigma * rng.standard_normal(kpts3d.shape)
    bbox_raw = _silhouette_box(camera, gt_raw_verts, rng, params.bbox_px)
    return SimDetections(
        person=np.asarray(idx), scores=np.zeros(n), bbox_raw=bbox_raw, bbox_rect=_rect_box(camera, bbox_raw),
        kpts2d_rect=k2, kpts2d_raw=distort_points(camera, k2), verts2d_rect=v2.astype(np.float32),
        verts2d_raw=distort_points(camera, v2).astype(np.float32), kpts3d=kpts3d,
        verts3d=(depth * vc).astype(np.float32),
        cam_t=(depth * kc.mean(axis=1, keepdims=True))[:, 0])


def _silhouette_box(camera: Camera, raw: np.ndarray, rng, jitter_px: float) -> np.ndarray:
    """(N,4) raw px boxes of the projected vertices clipped to the image (truncated at borders)."""
    if raw.shape[0] == 0:
        return np.zeros((0, 4))
    with np.errstate(invalid="ignore"):
        box = np.stack([np.nanmin(raw[..., 0], 1), np.nanmin(raw[..., 1], 1), np.nanmax(raw[..., 0], 1),
                        np.nanmax(raw[..., 1], 1)], axis=1)
    if jitter_px > 0:
        box = box + jitter_px * rng.standard_normal(box.shape)
    box[:, [0, 2]] = np.clip(box[:, [0, 2]], 0, camera.width - 1)
    box[:, [1, 3]] = np.clip(box[:, [1, 3]], 0, camera.height - 1)
    lo, hi = np.minimum(box[:, :2], box[:, 2:]), np.maximum(box[:, :2], box[:, 2:])
    return np.concatenate([lo, hi], axis=1)


def _rect_box(camera: Camera, box_raw: np.ndarray) -> np.ndarray:
    """Raw box -> rectified box: same width/height, centre at the undistorted raw centre."""
    if box_raw.shape[0] == 0:
        return box_raw.copy()
    c = camera.undistort_points(0.5 * (box_raw[:, :2] + box_raw[:, 2:]))
    half = 0.5 * (box_raw[:, 2:] - box_raw[:, :2])
    return np.concatenate([c - half, c + half], axis=1)


def _scores(rng, params, is_player, occ, trunc) -> np.ndarray:
    n = len(is_player)
    if params.exact:
        return np.full(n, 0.95)
    mean = np.where(is_player, params.player_score[0], params.bystander_score[0])
    sd = np.where(is_player, params.player_score[1], params.bystander_score[1])
    s = mean + sd * rng.standard_normal(n) - 0.15 * occ - 0.3 * trunc
    return np.clip(s, 0.05, 0.995)


def _false_positives(camera, rng, params, body) -> SimDetections | None:
    """Spectator-like bodies off the court, visible in this camera only."""
    k = int(rng.poisson(params.fp_rate))
    if k == 0:
        return None
    tries = 12
    hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
    side = rng.integers(0, 4, tries)
    along = rng.uniform(-1, 1, tries)
    off = rng.uniform(1.8, 4.0, tries)
    x = np.where(side < 2, along * (hx + 2), np.where(side == 2, hx + off, -hx - off))
    y = np.where(side < 2, np.where(side == 0, hy + off, -hy - off), along * (hy + 2))
    h = rng.uniform(1.55, 1.9, tries)
    w = rng.uniform(0.9, 1.15, tries)
    heading = rng.uniform(-np.pi, np.pi, tries)
    ang = gait_angles(rng.uniform(0, 2, tries), rng.uniform(0, 2 * np.pi, tries), rng.uniform(0, 0.5, tries),
                      np.zeros(tries), rng.uniform(-0.5, 0.5, tries))
    state = PersonState(h, w, np.stack([x, y], 1), heading, ang, np.zeros(tries, bool))
    skel = forward_kinematics(h, w, ang, state.root_xy, heading)
    verts = body.vertices(skel, h, w)
    raw = project_raw(camera, verts)
    ok = np.flatnonzero(~np.any(np.isnan(raw[..., 0]), axis=1) & (inside_image(camera, raw).mean(axis=1) > 0.6))
    if len(ok) == 0:
        return None
    idx = ok[:k]
    det = _estimate(camera, rng, params, body, state, idx, skel.keypoints, raw[idx], np.zeros(len(idx)))
    det.person = np.full(len(idx), -1)
    det.visible_fraction = np.ones(len(idx))
    hi = rng.random(len(idx)) < 0.08
    det.scores = np.where(hi, rng.uniform(0.85, 0.93, len(idx)), rng.uniform(0.25, 0.85, len(idx)))
    return det


_FIELDS = ("person", "scores", "bbox_raw", "bbox_rect", "kpts2d_rect", "kpts2d_raw", "verts2d_rect",
           "verts2d_raw", "kpts3d", "verts3d", "cam_t", "visible_fraction")


def _concat(a: SimDetections, b: SimDetections) -> SimDetections:
    return SimDetections(**{f: np.concatenate([getattr(a, f), getattr(b, f)]) for f in _FIELDS})


def _take(d: SimDetections, order: np.ndarray) -> SimDetections:
    return SimDetections(**{f: np.asarray(getattr(d, f))[order] for f in _FIELDS})


__all__ = ["NoiseParams", "PRESETS", "get_preset", "PersonState", "SimDetections", "simulate", "visibility"]
