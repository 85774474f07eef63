"""Detection-noise model of a monocular mesh-recovery frontend (SAM 3D Body-like).

For one camera and frame, every person is first tested for visibility: a fixed sample of its
surface vertices is projected; a sample counts as visible when it is inside the raw image and
not covered by a part box (per body part bbox) of a person nearer to the camera. A person is
missed when its visible fraction is below ``min_visible`` (mostly occluded or outside the
image) or when it is smaller than ``min_height_px`` (too far away), plus a small random miss rate
that grows with occlusion.

A detected person's estimate is the body model re-posed with noisy joint angles, re-centred on
the true keypoint centroid (the estimator fits the image), then scaled about the camera centre
by (1 + e), e ~ N(0, ``depth_sigma``): the root depth error along the viewing ray, invisible in
2D as for a real monocular estimate. Keypoints and mesh are one noisy body: every pose error
below (angles, gross limb errors) moves the keypoints AND the vertices of that body part.

Heteroscedastic, per body part (a real monocular mesh-recovery model is most accurate on the
large, rarely occluded torso; hands, fingers, feet and face details are small in the image, often
occluded or blurred, and much noisier):
- joint angles: N(0, ``angle_sigma`` x ANGLE_SCALE[angle]): torso lean/twist 0.6, hips 0.8,
  knees / shoulders 1.0, elbows 1.2, head yaw/pitch 1.5, ankles 2.0, wrists 2.5, finger curl 4.0;
  shape: ``shape_sigma`` relative error on height and width; body yaw: ``heading_sigma``;
- per-joint / per-vertex jitter scaled by the noise group (body.NOISE_GROUPS, ``group_scale``):
  torso 0.6, limb (elbows, knees) 1.0, extremity (wrists, ankles) 1.3, face (nose, eyes, ears;
  head vertices) 1.6, foot (heels, toes) 2.0, hand (fingers; hand vertices) 2.5 times
  ``kpt3d_sigma`` m (3D keypoints), ``kpt2d_px`` px (2D keypoints) and ``vert2d_px`` px (2D
  vertices), the 2D jitter x (1 + 2 x occluded fraction);
- gross limb errors: with probability ``gross_rate`` x (1 + 2 x occluded fraction) per detection,
  one limb (an arm with its hand, or a leg with its foot, uniform) is wrong: half of the time it
  takes the opposite limb's pose (left/right confusion), otherwise a hallucinated pose (uniform
  plausible angles). ``SimDetections.gross_limb`` records it.
Boxes come from the true silhouette (raw px, clipped to the image: truncated at borders) plus
``bbox_px`` edge jitter.

Scores: players N(0.95, 0.025), bystanders N(0.84, 0.07), minus 0.15 x occluded fraction and
0.3 x truncated fraction, clipped to [0.05, 0.995]. False positives: Poisson(``fp_rate``) per
image, spectator-like bodies off the court with scores U(0.25, 0.85) (8 % U(0.85, 0.93)).

Presets (angle_sigma rad / kpt3d_sigma m / depth_sigma / kpt2d_px / vert2d_px / gross_rate /
min_visible / fp_rate):
none 0 / 0 / 0 / 0 / 0 / 0 / - / 0 (exact: no noise, no misses, no false positives, score 0.95);
easy 0.05 / 0.008 / 0.06 / 0.6 / 0.3 / 0.02 / 0.15 / 0.1;
medium 0.09 / 0.014 / 0.12 / 1.0 / 0.5 / 0.05 / 0.25 / 0.3;
hard 0.15 / 0.02 / 0.15 / 2.0 / 1.0 / 0.1 / 0.4 / 0.8 (group_scale the same for all).

Measured at medium (sportcenter6, seed 11, test/test_sim_noise.py checks the ranges):
PA-MPJPE on the body joints (COCO-17, as mesh-recovery benchmarks report it) mean 47 mm (range
40-60); on all 70 MHR70 joints 77 mm (42 of them hands / feet); median |root depth error| 8 % of
the distance (5-15 %); median 2D keypoint error 3.4 px, vertex error 2.2 px (1-6 px); median 2D
error per group, keypoints / vertices: torso 1.9 / 1.8, limb 2.2 / 1.9, extremity 3.2 / -, face
2.9 / 2.5, foot 4.3 / 3.7, hand 4.1 / 2.9 px; gross limb errors on 6 % of the detections; misses
1 % (sportcenter6) and 5 % (humanm3_4, whose person-height cameras see more occlusion).
Easy / hard body PA-MPJPE: about 26 / 76 mm (all 70: 44 / 120 mm).
Everything is deterministic per (seed, camera index, frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from maem_ros.core.geometry.camera import Camera

from .body import ANGLE_KEYS, JOINT_GROUP, BodyModel, Skeleton, forward_kinematics, gait_angles
from .occlusion import sample_view
from .rigs import COURT_LENGTH, COURT_WIDTH
from .view import (
    camera_to_normalised_xy,
    camera_to_rectified,
    camera_to_rectified_xy,
    distort_points,
    inside_image_xy,
    normalised_to_raw_xy,
    project_raw_xy,
    world_to_camera,
)

_SAMPLES_PER_PART = 12

#: relative angle noise per joint angle (x ``angle_sigma``): the torso is estimated best; distal,
#: small joints (wrists, ankles, fingers) and the head orientation worst
ANGLE_SCALE = {
    "lean": 0.6,
    "side_lean": 0.6,
    "twist": 0.6,
    "head_yaw": 1.5,
    "head_pitch": 1.5,
    "hip_flex_l": 0.8,
    "hip_flex_r": 0.8,
    "hip_abd_l": 0.8,
    "hip_abd_r": 0.8,
    "knee_l": 1.0,
    "knee_r": 1.0,
    "ankle_l": 2.0,
    "ankle_r": 2.0,
    "sh_flex_l": 1.0,
    "sh_flex_r": 1.0,
    "sh_abd_l": 1.0,
    "sh_abd_r": 1.0,
    "elbow_l": 1.2,
    "elbow_r": 1.2,
    "wrist_l": 2.5,
    "wrist_r": 2.5,
    "finger_curl": 4.0,
}
assert set(ANGLE_SCALE) == set(ANGLE_KEYS)
#: the joint angles of each limb (gross errors): left arm, right arm, left leg, right leg
_LIMBS = (
    ("sh_flex_l", "sh_abd_l", "elbow_l", "wrist_l"),
    ("sh_flex_r", "sh_abd_r", "elbow_r", "wrist_r"),
    ("hip_flex_l", "hip_abd_l", "knee_l", "ankle_l"),
    ("hip_flex_r", "hip_abd_r", "knee_r", "ankle_r"),
)
#: uniform ranges (rad) of a hallucinated arm / leg pose, per angle of _LIMBS
_ARM_RANGE = ((-0.6, 2.8), (0.0, 1.2), (0.0, 2.0), (-0.5, 0.8))
_LEG_RANGE = ((-0.4, 1.4), (0.0, 0.45), (0.0, 1.8), (-0.4, 0.5))


@dataclass(frozen=True)
class NoiseParams:
    """One difficulty preset (units: rad, m, px, fractions, detections per image)."""

    exact: bool = False
    angle_sigma: float = 0.09
    heading_sigma: float = 0.05
    shape_sigma: float = 0.03
    kpt3d_sigma: float = 0.014
    depth_sigma: float = 0.12
    kpt2d_px: float = 1.0
    vert2d_px: float = 0.5
    bbox_px: float = 2.0
    group_scale: tuple[float, ...] = (0.6, 1.0, 1.3, 1.6, 2.0, 2.5)
    gross_rate: float = 0.05
    min_visible: float = 0.25
    min_height_px: float = 20.0
    miss_rate: float = 0.01
    fp_rate: float = 0.3
    player_score: tuple[float, float] = (0.95, 0.025)
    bystander_score: tuple[float, float] = (0.84, 0.07)


PRESETS: dict[str, NoiseParams] = {
    "none": NoiseParams(
        exact=True,
        angle_sigma=0.0,
        heading_sigma=0.0,
        shape_sigma=0.0,
        kpt3d_sigma=0.0,
        depth_sigma=0.0,
        kpt2d_px=0.0,
        vert2d_px=0.0,
        bbox_px=0.0,
        gross_rate=0.0,
        min_visible=0.0,
        miss_rate=0.0,
        fp_rate=0.0,
    ),
    "easy": NoiseParams(
        angle_sigma=0.05,
        heading_sigma=0.03,
        shape_sigma=0.02,
        kpt3d_sigma=0.008,
        depth_sigma=0.06,
        kpt2d_px=0.6,
        vert2d_px=0.3,
        bbox_px=1.0,
        gross_rate=0.02,
        min_visible=0.15,
        min_height_px=16.0,
        miss_rate=0.005,
        fp_rate=0.1,
    ),
    "medium": NoiseParams(),
    "hard": NoiseParams(
        angle_sigma=0.15,
        heading_sigma=0.09,
        shape_sigma=0.05,
        kpt3d_sigma=0.02,
        depth_sigma=0.15,
        kpt2d_px=2.0,
        vert2d_px=1.0,
        bbox_px=4.0,
        gross_rate=0.1,
        min_visible=0.4,
        min_height_px=28.0,
        miss_rate=0.03,
        fp_rate=0.8,
        player_score=(0.93, 0.035),
        bystander_score=(0.8, 0.08),
    ),
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
class VertexSource:
    """Float64 vertex data of M estimates, behind the (lazy) vertex outputs of SimDetections.

    rect_px (M,V,2) noisy rectified px and rect_f32 its float32; cam_m (M,3,V) camera-frame m
    before the depth error, component-major; depth (M,) the depth-error scale; camera: the lens.
    """

    camera: Camera
    rect_px: np.ndarray
    rect_f32: np.ndarray
    cam_m: np.ndarray
    depth: np.ndarray

    def __len__(self) -> int:
        return len(self.depth)

    def concat(self, other: VertexSource) -> VertexSource:
        return VertexSource(
            self.camera,
            *(
                np.concatenate([getattr(self, f), getattr(other, f)])
                for f in ("rect_px", "rect_f32", "cam_m", "depth")
            ),
        )


@dataclass
class SimDetections:
    """Simulated detections of one camera/frame (N detections, 70 keypoints, V vertices).

    person (N,) GT person index, -1 = false positive; bbox_raw (N,4) raw px; bbox_rect (N,4)
    rectified px (raw box moved so its centre is the undistorted raw centre); kpts2d/verts2d
    _rect and _raw px; kpts3d (N,70,3) / verts3d (N,V,3) camera frame m; cam_t (N,3) m;
    gross_limb (N,) the limb with a gross pose error (0 left arm, 1 right arm, 2 left leg, 3 right
    leg) or -1. The vertex outputs verts2d_rect, verts2d_raw and verts3d (float32) are taken from
    the rows ``verts_rows`` (N,) of ``verts_source`` on first access (the frontends never need the last
    two; permuting or concatenating detections moves no mesh data).
    """

    person: np.ndarray
    scores: np.ndarray
    bbox_raw: np.ndarray
    bbox_rect: np.ndarray
    kpts2d_rect: np.ndarray
    kpts2d_raw: np.ndarray
    kpts3d: np.ndarray
    cam_t: np.ndarray
    verts_source: VertexSource
    verts_rows: np.ndarray
    visible_fraction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gross_limb: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    _lazy: dict = field(default_factory=dict, repr=False)

    def _once(self, key: str, make) -> np.ndarray:
        if key not in self._lazy:
            self._lazy[key] = make()
        return self._lazy[key]

    @property
    def verts2d_rect(self) -> np.ndarray:
        """(N,V,2) float32 rectified px of the vertices."""
        return self._once("rect", lambda: self.verts_source.rect_f32[self.verts_rows])

    @property
    def verts2d_raw(self) -> np.ndarray:
        """(N,V,2) float32 raw px of the vertices (the distorted float64 rectified px)."""
        src, rows = self.verts_source, self.verts_rows
        return self._once("raw", lambda: distort_points(src.camera, src.rect_px[rows]).astype(np.float32))

    @property
    def verts3d(self) -> np.ndarray:
        """(N,V,3) float32 camera-frame m of the vertices (with the depth error)."""
        src, rows = self.verts_source, self.verts_rows
        return self._once(
            "3d", lambda: _scaled_f32(src.depth[rows, None, None], src.cam_m[rows].transpose(0, 2, 1))
        )


def simulate(
    camera: Camera,
    rng: np.random.Generator,
    params: NoiseParams,
    body: BodyModel,
    state: PersonState,
    gt_points: np.ndarray,
    gt_verts: np.ndarray | None = None,
    gt_skel: Skeleton | None = None,
) -> SimDetections:
    """Detections of one camera: gt_points (P,70+,3) world m (keypoints first); the true meshes
    either as gt_verts (P,V,3) world m or, faster (no world mesh), as the skeletons gt_skel that
    ``body`` poses them from (then equal up to float64 rounding)."""
    sample_idx = body.part_vertex_sample(_SAMPLES_PER_PART)
    samples, gt_cam = _true_mesh(camera, body, state, sample_idx, gt_verts, gt_skel)
    vis, in_img, sample_v = sample_view(camera, samples, body.part_of[sample_idx], len(body.slices))
    # every vertex once: the fold test, then the silhouette boxes of the detected persons
    gt_x, gt_y, gt_ok = camera_to_normalised_xy(camera, gt_cam.transpose(0, 2, 1))
    beyond_fold = ~np.all(gt_ok, axis=1)  # lens fold: no consistent raw px
    occ = np.clip(1.0 - vis / np.maximum(in_img, 1e-9), 0.0, 1.0)
    trunc = 1.0 - in_img
    if params.exact:
        detected = (in_img > 0) & ~beyond_fold
    else:
        u = rng.random(len(vis))
        with np.errstate(invalid="ignore"):
            extent = np.fmax.reduce(sample_v, axis=1) - np.fmin.reduce(sample_v, axis=1)  # nanmax - nanmin
            tall = np.nan_to_num(extent) >= params.min_height_px
        detected = (vis >= params.min_visible) & tall & ~beyond_fold & (u >= params.miss_rate * (1 + 4 * occ))
    idx = np.flatnonzero(detected)
    gt_raw = normalised_to_raw_xy(camera, gt_x[idx], gt_y[idx], gt_ok[idx])
    dets = _estimate(camera, rng, params, body, state, idx, gt_points[:, :70], gt_raw, occ[idx])
    dets.person = idx
    dets.visible_fraction = vis[idx]
    dets.scores = _scores(rng, params, state.is_player[idx], occ[idx], trunc[idx])
    if not params.exact:
        fp = _false_positives(camera, rng, params, body)
        if fp is not None:
            dets = _concat(dets, fp)
    order = rng.permutation(len(dets.person))
    return _take(dets, order)


def _true_mesh(
    camera: Camera,
    body: BodyModel,
    state: PersonState,
    sample_idx: np.ndarray,
    gt_verts: np.ndarray | None,
    gt_skel: Skeleton | None,
) -> tuple[np.ndarray, np.ndarray]:
    """World m samples (P,S,3) (vertices ``sample_idx``) and camera-frame m vertices (P,3,V) of the
    true meshes, from gt_verts (P,V,3) world m or, when given, from the skeletons gt_skel."""
    if gt_skel is not None:
        return (
            body.vertices_subset(gt_skel, state.height, state.width, sample_idx),
            _camera_vertices(camera, body, gt_skel, state.height, state.width),
        )
    if gt_verts is None:
        raise ValueError("simulate: needs gt_verts or gt_skel")
    return gt_verts[:, sample_idx], world_to_camera(camera, gt_verts).transpose(0, 2, 1)


def _estimate(camera, rng, params, body, state, idx, gt_kpts, gt_raw_verts, occ) -> SimDetections:
    """Noisy estimates of persons ``idx``; gt_raw_verts: raw px (u, v) each (n,V) of their true mesh."""
    n = len(idx)
    sub_angles = {k: state.angles[k][idx] for k in ANGLE_KEYS}
    gross = np.full(n, -1)
    if params.exact:
        h, w, yaw, ang = state.height[idx], state.width[idx], state.heading[idx], sub_angles
    else:
        h = state.height[idx] * (1 + params.shape_sigma * rng.standard_normal(n))
        w = state.width[idx] * (1 + params.shape_sigma * rng.standard_normal(n))
        yaw = state.heading[idx] + params.heading_sigma * rng.standard_normal(n)
        ang = {
            k: v + ANGLE_SCALE[k] * params.angle_sigma * rng.standard_normal(n) for k, v in sub_angles.items()
        }
        gross = _gross_limb_errors(rng, ang, params.gross_rate * (1 + 2 * occ))
    skel = forward_kinematics(h, w, ang, state.root_xy[idx], yaw)
    kp = skel.keypoints
    shift = gt_kpts[idx].mean(axis=1, keepdims=True) - kp.mean(axis=1, keepdims=True)
    kp = kp + shift  # the estimator fits the person's image position
    depth_n = 1.0 + (0.0 if params.exact else np.clip(params.depth_sigma * rng.standard_normal(n), -0.4, 0.4))
    depth = np.broadcast_to(depth_n, (n,))[:, None, None]
    kc = world_to_camera(camera, kp)
    vc = _camera_vertices(camera, body, skel, h, w, shift)  # (n,3,V)
    jit = 1.0 + 2.0 * occ[:, None, None]
    gscale = np.asarray(params.group_scale, dtype=np.float64)
    kscale = gscale[JOINT_GROUP][None, :, None]  # (1,70,1)
    k2 = camera_to_rectified(camera, kc) + params.kpt2d_px * kscale * jit * rng.standard_normal(
        kp.shape[:2] + (2,)
    )
    v2 = np.stack(camera_to_rectified_xy(camera, vc.transpose(0, 2, 1)), axis=-1)
    if params.vert2d_px > 0:
        z = rng.standard_normal(v2.shape).reshape(n, -1)  # (n, 2V): u, v of vertex k at 2k, 2k+1
        z *= _vertex_scale2(body, params.group_scale)  # per vertex, by noise group
        z *= params.vert2d_px * jit[:, :, 0]  # per detection, by occlusion
        v2 += z.reshape(v2.shape)
    kpts3d = depth * kc
    if params.kpt3d_sigma > 0:
        kpts3d = kpts3d + params.kpt3d_sigma * kscale * rng.standard_normal(kpts3d.shape)
    u_raw, v_raw = gt_raw_verts
    bbox_raw = _silhouette_box(camera, u_raw, v_raw, rng, params.bbox_px)
    return SimDetections(
        person=np.asarray(idx),
        scores=np.zeros(n),
        bbox_raw=bbox_raw,
        bbox_rect=_rect_box(camera, bbox_raw),
        kpts2d_rect=k2,
        kpts2d_raw=distort_points(camera, k2),
        kpts3d=kpts3d,
        cam_t=(depth * kc.mean(axis=1, keepdims=True))[:, 0],
        verts_source=VertexSource(camera, v2, v2.astype(np.float32), vc, np.array(depth[:, 0, 0])),
        verts_rows=np.arange(n),
        gross_limb=gross,
    )


def _gross_limb_errors(rng: np.random.Generator, ang: dict[str, np.ndarray], rate: np.ndarray) -> np.ndarray:
    """Gross limb errors, in place on the noisy angles ``ang`` (n persons): with probability
    ``rate`` (n,) one limb (arm or leg, uniform) is wrong, half of the time with the pose of the
    opposite limb (left/right confusion), else with a hallucinated pose (uniform plausible angles).
    Keypoints and mesh come from the same angles, so both show the error. Returns (n,) the limb
    index (0 left arm, 1 right arm, 2 left leg, 3 right leg) or -1. Always draws the same numbers
    per person (deterministic per seed whatever the rate)."""
    n = len(rate)
    hit = rng.random(n) < rate
    limb = rng.integers(0, 4, n)
    swap = rng.random(n) < 0.5
    u = rng.random((n, 4))
    for i in np.flatnonzero(hit):
        names, other = _LIMBS[limb[i]], _LIMBS[limb[i] ^ 1]
        rng_ = _ARM_RANGE if limb[i] < 2 else _LEG_RANGE
        for j, (k, ko) in enumerate(zip(names, other)):
            ang[k][i] = ang[ko][i] if swap[i] else rng_[j][0] + u[i, j] * (rng_[j][1] - rng_[j][0])
    return np.where(hit, limb, -1)


def _camera_vertices(
    camera: Camera,
    body: BodyModel,
    skel: Skeleton,
    height: np.ndarray,
    width: np.ndarray,
    shift: np.ndarray | None = None,
) -> np.ndarray:
    """(n,3,V) camera-frame m, component-major, of the meshes of ``skel`` moved by ``shift`` (n,1,3)
    world m: the part maps are moved into the camera frame, so each vertex costs one small product
    (equal to ``world_to_camera`` of ``body.vertices`` up to float64 rounding)."""
    M = body.part_frames(skel, height, width)  # (n,K,3,4) world
    if shift is not None:
        M[..., 0] += shift  # anchors (n,1,3) -> broadcast over the parts
    Mc = np.matmul(camera.R, M)  # rotate every column
    Mc[..., 0] += camera.t
    return body.evaluate_components(Mc)


def _vertex_scale2(body: BodyModel, group_scale: tuple[float, ...]) -> np.ndarray:
    """(2V,) the group scale of each vertex, repeated for its u and v (cached per body and scales)."""
    cache = body.__dict__.setdefault("_noise_scale2", {})
    key = tuple(float(g) for g in group_scale)
    if key not in cache:
        cache[key] = np.repeat(np.asarray(key)[body.group_of], 2)
    return cache[key]


def _scaled_f32(scale: np.ndarray, x: np.ndarray) -> np.ndarray:
    """float32 of scale * x, the product taken in float64 (one pass, no float64 temporary)."""
    return np.multiply(
        scale,
        x,
        out=np.empty(np.broadcast_shapes(np.shape(scale), x.shape), np.float32),
        dtype=np.float64,
        casting="unsafe",
    )


def _silhouette_box(camera: Camera, u: np.ndarray, v: np.ndarray, rng, jitter_px: float) -> np.ndarray:
    """(N,4) raw px boxes of the projected vertices (raw px u, v (N,V), NaN ignored) clipped to the
    image (truncated at borders)."""
    if u.shape[0] == 0:
        return np.zeros((0, 4))
    with np.errstate(invalid="ignore"):
        box = np.stack([np.nanmin(u, 1), np.nanmin(v, 1), np.nanmax(u, 1), np.nanmax(v, 1)], axis=1)
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
    ang = gait_angles(
        rng.uniform(0, 2, tries),
        rng.uniform(0, 2 * np.pi, tries),
        rng.uniform(0, 0.5, tries),
        np.zeros(tries),
        rng.uniform(-0.5, 0.5, tries),
    )
    state = PersonState(h, w, np.stack([x, y], 1), heading, ang, np.zeros(tries, bool))
    skel = forward_kinematics(h, w, ang, state.root_xy, heading)
    idx, raw = _first_in_view(camera, body, skel, h, w, k)
    if len(idx) == 0:
        return None
    det = _estimate(camera, rng, params, body, state, idx, skel.keypoints, raw, np.zeros(len(idx)))
    det.person = np.full(len(idx), -1)
    det.visible_fraction = np.ones(len(idx))
    hi = rng.random(len(idx)) < 0.08
    det.scores = np.where(hi, rng.uniform(0.85, 0.93, len(idx)), rng.uniform(0.25, 0.85, len(idx)))
    return det


def _first_in_view(
    camera: Camera, body: BodyModel, skel: Skeleton, height: np.ndarray, width: np.ndarray, k: int
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The first ``k`` candidate bodies (in order) fully in front of the lens fold and > 60 % inside
    the raw image: their indices (m,) and raw px (u, v) each (m,V). Meshes are evaluated one
    candidate at a time, only until ``k`` are found."""
    found: list[int] = []
    us, vs = [], []
    for i in range(len(height)):
        if len(found) == k:
            break
        one = Skeleton(skel.points[i : i + 1], skel.refs[i : i + 1])
        u, v = project_raw_xy(camera, body.vertices(one, height[i : i + 1], width[i : i + 1]))
        if not np.isnan(u).any() and inside_image_xy(camera, u, v).mean() > 0.6:
            found.append(i)
            us.append(u)
            vs.append(v)
    if not found:
        return np.zeros(0, int), (np.zeros((0, body.num_vertices)), np.zeros((0, body.num_vertices)))
    return np.array(found), (np.concatenate(us), np.concatenate(vs))


#: per-detection array fields (the vertex outputs follow verts_rows)
_FIELDS = (
    "person",
    "scores",
    "bbox_raw",
    "bbox_rect",
    "kpts2d_rect",
    "kpts2d_raw",
    "kpts3d",
    "cam_t",
    "visible_fraction",
    "gross_limb",
)


def _concat(a: SimDetections, b: SimDetections) -> SimDetections:
    return SimDetections(
        **{f: np.concatenate([getattr(a, f), getattr(b, f)]) for f in _FIELDS},  # type: ignore[arg-type]  # _FIELDS: array fields
        verts_source=a.verts_source.concat(b.verts_source),
        verts_rows=np.concatenate([a.verts_rows, b.verts_rows + len(a.verts_source)]),
    )


def _take(d: SimDetections, order: np.ndarray) -> SimDetections:
    return SimDetections(
        **{f: np.asarray(getattr(d, f))[order] for f in _FIELDS},
        verts_source=d.verts_source,
        verts_rows=d.verts_rows[order],
    )


__all__ = ["NoiseParams", "PRESETS", "get_preset", "PersonState", "SimDetections", "VertexSource", "simulate"]
