"""Articulated body with a FIXED-topology surface, driven by the 70-keypoint MHR70 skeleton.

Skeleton: forward kinematics from joint angles (radians) and a body shape (height m, width
scale), all vectorised over persons. Person-local frame: x forward, y left, z up; world = court
frame (z up, metres) after the heading rotation and root translation; the lowest sole point
touches the floor (z = 0).

Surface: ``V`` vertices spread over 19 rounded parts (head, neck, chest, abdomen, pelvis, upper
arms, forearms, hands, thighs, shins, feet). Vertex k has fixed parameters (part, position along
the part's axis, angle around it), so it is the same body spot in every frame and for every
person: its distance to its part's axis is constant over time (only the per-person shape scales
it). Evaluation is one small matmul per part.

Vertex density per part follows a real parametric body mesh, not surface area (``PART_SHARE``).
Like SMPL-X, MHR (the mesh SAM 3D Body outputs) spends a large share of its vertices on the head
and hands. Per-part counts of the MHR mesh were not found; the shares follow SMPL-X (10,475
vertices), whose head is the FLAME head mesh and whose hands are MANO meshes (the correspondence
files ``SMPL-X__FLAME_vertex_ids.npy`` and ``MANO_SMPLX_vertex_ids.pkl`` shipped with SMPL-X,
Pavlakos et al. CVPR 2019): FLAME region 5,023 vertices (Li et al. 2017; 48 %, face, scalp, eyes
and neck), MANO 778 vertices per hand (Romero et al. 2017; 7.4 % each). Here: head 42 %, neck 6 %,
each hand 7.4 %, each foot 2.5 % (the SMPL-style foot + toe segments; approximate), the remaining
32.2 % on torso and limbs by surface area. The torso (chest, abdomen, pelvis, shoulders, hip band)
thus holds about 16 % of the vertices instead of 43 % by area.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from maem_ros.core.skeleton import MHR70_NAMES

J = len(MHR70_NAMES)
_IDX = {n: i for i, n in enumerate(MHR70_NAMES)}
#: points computed beyond the 70 keypoints (anchors of surface parts), appended after them
EXTRA_POINTS = (
    "pelvis",
    "spine_mid",
    "ear_mid",
    "chin",
    "head_top",
    "head_bottom",
    "left_toe_mid",
    "right_toe_mid",
    "left_hand_end",
    "right_hand_end",
)
_PT = {**_IDX, **{n: J + i for i, n in enumerate(EXTRA_POINTS)}}
#: reference vectors (world) that fix the angular origin of each part
REFS = ("pelvis_lateral", "torso_lateral", "head_lateral", "pelvis_forward")

ANGLE_KEYS = (
    "lean",
    "side_lean",
    "twist",
    "head_yaw",
    "head_pitch",
    "hip_flex_l",
    "hip_flex_r",
    "hip_abd_l",
    "hip_abd_r",
    "knee_l",
    "knee_r",
    "ankle_l",
    "ankle_r",
    "sh_flex_l",
    "sh_flex_r",
    "sh_abd_l",
    "sh_abd_r",
    "elbow_l",
    "elbow_r",
    "wrist_l",
    "wrist_r",
    "finger_curl",
)

# (name, anchor a, anchor b, radius along e1, radius along e2, reference, cap extension) at 1.8 m
PARTS: tuple[tuple[str, str, str, float, float, str, float], ...] = (
    ("head", "head_bottom", "head_top", 0.078, 0.095, "head_lateral", 0.05),
    ("neck", "neck", "head_bottom", 0.055, 0.058, "head_lateral", 0.0),
    ("chest", "spine_mid", "neck", 0.165, 0.11, "torso_lateral", 0.08),
    ("abdomen", "pelvis", "spine_mid", 0.15, 0.10, "torso_lateral", 0.05),
    ("pelvis", "left_hip", "right_hip", 0.105, 0.09, "pelvis_forward", 0.45),
    ("upper_arm_l", "left_shoulder", "left_elbow", 0.048, 0.05, "torso_lateral", 0.12),
    ("upper_arm_r", "right_shoulder", "right_elbow", 0.048, 0.05, "torso_lateral", 0.12),
    ("forearm_l", "left_elbow", "left_wrist", 0.04, 0.037, "torso_lateral", 0.05),
    ("forearm_r", "right_elbow", "right_wrist", 0.04, 0.037, "torso_lateral", 0.05),
    ("hand_l", "left_wrist", "left_hand_end", 0.018, 0.043, "torso_lateral", 0.15),
    ("hand_r", "right_wrist", "right_hand_end", 0.018, 0.043, "torso_lateral", 0.15),
    ("thigh_l", "left_hip", "left_knee", 0.078, 0.082, "pelvis_lateral", 0.08),
    ("thigh_r", "right_hip", "right_knee", 0.078, 0.082, "pelvis_lateral", 0.08),
    ("shin_l", "left_knee", "left_ankle", 0.054, 0.058, "pelvis_lateral", 0.05),
    ("shin_r", "right_knee", "right_ankle", 0.054, 0.058, "pelvis_lateral", 0.05),
    ("foot_l", "left_heel", "left_toe_mid", 0.045, 0.04, "pelvis_lateral", 0.08),
    ("foot_r", "right_heel", "right_toe_mid", 0.045, 0.04, "pelvis_lateral", 0.08),
    ("shoulders", "left_shoulder", "right_shoulder", 0.06, 0.07, "pelvis_forward", 0.1),
    ("hips_band", "left_hip", "right_hip", 0.12, 0.10, "pelvis_forward", 0.25),
)
PART_NAMES = tuple(p[0] for p in PARTS)
#: fixed vertex shares (see the module docstring: SMPL-X FLAME / MANO counts); every other part
#: shares the rest by template surface area
PART_SHARE = {
    "head": 0.42,
    "neck": 0.06,
    "hand_l": 778 / 10475,
    "hand_r": 778 / 10475,
    "foot_l": 0.025,
    "foot_r": 0.025,
}
#: noise group of each surface part and of each MHR70 keypoint (sim/noise.py scales errors by group)
NOISE_GROUPS = ("torso", "limb", "extremity", "face", "foot", "hand")
PART_GROUP = {
    "head": "face",
    "neck": "torso",
    "chest": "torso",
    "abdomen": "torso",
    "pelvis": "torso",
    "upper_arm_l": "limb",
    "upper_arm_r": "limb",
    "forearm_l": "limb",
    "forearm_r": "limb",
    "hand_l": "hand",
    "hand_r": "hand",
    "thigh_l": "limb",
    "thigh_r": "limb",
    "shin_l": "limb",
    "shin_r": "limb",
    "foot_l": "foot",
    "foot_r": "foot",
    "shoulders": "torso",
    "hips_band": "torso",
}


def _joint_group(name: str) -> str:
    if name in ("nose", "left_eye", "right_eye", "left_ear", "right_ear"):
        return "face"
    if name.endswith(("_wrist", "_ankle")):
        return "extremity"
    if name.endswith(("_heel", "_toe_tip")):
        return "foot"
    if any(f in name for f in ("thumb", "index", "middle", "ring", "pinky")):
        return "hand"
    if name.endswith(("_elbow", "_knee", "_olecranon", "_cubital_fossa")):
        return "limb"
    return "torso"  # shoulders, acromions, hips, neck


#: (70,) noise group index (into NOISE_GROUPS) of each MHR70 keypoint
JOINT_GROUP = np.array([NOISE_GROUPS.index(_joint_group(n)) for n in MHR70_NAMES])
#: part -> colour class used by the renderer: 0 skin, 1 jersey, 2 shorts, 3 shoes, 4 hair
PART_CLASS = {
    "head": 0,
    "neck": 0,
    "chest": 1,
    "abdomen": 1,
    "pelvis": 2,
    "upper_arm_l": 1,
    "upper_arm_r": 1,
    "forearm_l": 0,
    "forearm_r": 0,
    "hand_l": 0,
    "hand_r": 0,
    "thigh_l": 2,
    "thigh_r": 2,
    "shin_l": 0,
    "shin_r": 0,
    "foot_l": 3,
    "foot_r": 3,
    "shoulders": 1,
    "hips_band": 2,
}


@dataclass
class Skeleton:
    """FK result: points (P, 70 + len(EXTRA_POINTS), 3) world m; refs (P, 4, 3) unit vectors."""

    points: np.ndarray
    refs: np.ndarray

    @property
    def keypoints(self) -> np.ndarray:
        """(P,70,3) MHR70 keypoints, world metres."""
        return self.points[:, :J]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (3-vectors): the products and differences of ``np.cross``, without
    its overhead on small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _lin(*terms) -> np.ndarray:
    """sum of coefficient (P,) or scalar times vector (P,3)."""
    out: Any = 0.0  # the sum becomes an array at the first vector term
    for c, v in terms:
        out = out + (c[..., None] if isinstance(c, np.ndarray) else c) * v
    return out


def _placement(
    pts: np.ndarray, heading: np.ndarray, root_xy: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(P,3,3) heading rotation about z and (P,3) world translation (m) that put P bodies'
    points (P,K,3, pelvis-centred, m) on the floor (lowest sole point 0.012 s m above z = 0) at
    root_xy (P,2) m facing heading (P,) rad."""
    P = pts.shape[0]
    soles = pts[:, [_IDX[n] for n in _SOLE_POINTS], 2]
    lift = -soles.min(axis=1) + 0.012 * s
    c, sn = np.cos(heading), np.sin(heading)
    Rz = np.stack(
        [
            np.stack([c, -sn, np.zeros(P)], -1),
            np.stack([sn, c, np.zeros(P)], -1),
            np.broadcast_to([0.0, 0.0, 1.0], (P, 3)),
        ],
        axis=1,
    )
    offset = np.concatenate([np.asarray(root_xy, dtype=np.float64), lift[:, None]], axis=1)
    return Rz, offset


#: the points a standing body's soles touch the floor with
_SOLE_POINTS = (
    "left_heel",
    "right_heel",
    "left_big_toe_tip",
    "right_big_toe_tip",
    "left_small_toe_tip",
    "right_small_toe_tip",
)


def forward_kinematics(
    height: np.ndarray,
    width: np.ndarray,
    angles: dict[str, np.ndarray],
    root_xy: np.ndarray,
    heading: np.ndarray,
) -> Skeleton:
    """Joint angles -> world keypoints for P persons.

    height (P,) m; width (P,) scale (1 = average); angles: ANGLE_KEYS -> (P,) rad; root_xy (P,2)
    world m (pelvis ground position); heading (P,) rad (0 = facing +x, counter-clockwise).
    """
    missing = [k for k in ANGLE_KEYS if k not in angles]
    if missing:
        raise ValueError(f"angles: missing {', '.join(missing)}")
    H = np.asarray(height, dtype=np.float64)
    P = H.shape[0]
    s = H / 1.8  # all template lengths are for a 1.8 m person
    ws = np.asarray(width, dtype=np.float64) * s
    a = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), (P,)) for k, v in angles.items()}
    ex, ey, ez = (np.broadcast_to(np.eye(3)[i], (P, 3)) for i in range(3))
    pts = np.zeros((P, J + len(EXTRA_POINTS), 3))

    def put(name: str, value: np.ndarray) -> None:
        pts[:, _PT[name]] = value

    # torso frame: lean (pitch forward), side lean (roll), twist (yaw of the chest vs the pelvis)
    lean, roll, tw = a["lean"], a["side_lean"], a["twist"]
    f0 = _lin((np.cos(tw), ex), (np.sin(tw), ey))
    l0 = _lin((-np.sin(tw), ex), (np.cos(tw), ey))
    u_t = _unit(_lin((np.sin(lean), f0), (np.sin(roll), l0), (np.cos(lean) * np.cos(roll), ez)))
    l_t = _unit(l0 - np.sum(l0 * u_t, -1, keepdims=True) * u_t)
    f_t = _cross(l_t, u_t)

    put("pelvis", np.zeros((P, 3)))
    put("spine_mid", _lin((0.14 * H, u_t)))
    neck = _lin((0.305 * H, u_t))
    put("neck", neck)
    for side, sg in (("left", 1.0), ("right", -1.0)):
        sh = _lin((0.285 * H, u_t), (sg * 0.106 * H * np.asarray(width), l_t))
        put(f"{side}_shoulder", sh)
        put(f"{side}_acromion", sh + _lin((0.022 * s, u_t), (sg * 0.022 * ws, l_t)))
        _arm(put, side, sg, sh, a, H, s, f_t, l_t, u_t)
        hip = _lin((sg * 0.092 * ws, ey))
        put(f"{side}_hip", hip)
        _leg(put, side, sg, hip, a, H, s, ex, ey, ez)

    # head: yaw about the torso axis, then pitch (positive = looking down)
    yaw, pitch = a["head_yaw"], a["head_pitch"]
    fy = _lin((np.cos(yaw), f_t), (np.sin(yaw), l_t))
    l_h = _lin((np.cos(yaw), l_t), (-np.sin(yaw), f_t))
    f_h = _lin((np.cos(pitch), fy), (-np.sin(pitch), u_t))
    u_h = _cross(f_h, l_h)
    ear_mid = neck + _lin((0.082 * H, u_t))
    put("ear_mid", ear_mid)
    put("left_ear", ear_mid + _lin((0.072 * ws, l_h)))
    put("right_ear", ear_mid - _lin((0.072 * ws, l_h)))
    put("nose", ear_mid + _lin((0.10 * s, f_h), (-0.012 * s, u_h)))
    for side, sg in (("left", 1.0), ("right", -1.0)):
        put(f"{side}_eye", ear_mid + _lin((0.083 * s, f_h), (0.024 * s, u_h), (sg * 0.032 * s, l_h)))
    put("chin", ear_mid + _lin((0.06 * s, f_h), (-0.085 * s, u_h)))
    put("head_top", ear_mid + _lin((0.13 * s, u_h), (-0.01 * s, f_h)))
    put("head_bottom", ear_mid + _lin((-0.075 * s, u_h), (0.02 * s, f_h)))

    # feet on the floor, then the heading rotation and the root translation
    Rz, offset = _placement(pts, heading, root_xy, s)
    world = np.einsum("pij,pkj->pki", Rz, pts) + offset[:, None, :]
    refs = np.stack([ey, l_t, l_h, ex], axis=1)
    refs = np.einsum("pij,pkj->pki", Rz, refs)
    return Skeleton(points=world, refs=refs)


def _limb_dir(theta, beta, sg, f, l, u):  # noqa: E741 - f, l, u: front, lateral, up axes
    """Unit direction: flexion theta forward from 'down', abduction beta outward (side sign sg)."""
    return _lin((np.sin(theta) * np.cos(beta), f), (sg * np.sin(beta), l), (-np.cos(theta) * np.cos(beta), u))


def _front(theta, f, u):
    """Unit direction of increasing flexion at flexion theta (in the limb plane)."""
    return _lin((np.cos(theta), f), (np.sin(theta), u))


def _arm(put, side, sg, sh, a, H, s, f_t, l_t, u_t) -> None:
    th, be = a[f"sh_flex_{side[0]}"], a[f"sh_abd_{side[0]}"]
    el = np.maximum(a[f"elbow_{side[0]}"], 0.0)
    elbow = sh + _lin((0.186 * H, _limb_dir(th, be, sg, f_t, l_t, u_t)))
    put(f"{side}_elbow", elbow)
    n_el = _front(th + 0.5 * el, f_t, u_t)
    put(f"{side}_cubital_fossa", elbow + _lin((0.024 * s, n_el)))
    put(f"{side}_olecranon", elbow - _lin((0.03 * s, n_el)))
    wrist = elbow + _lin((0.146 * H, _limb_dir(th + el, be, sg, f_t, l_t, u_t)))
    put(f"{side}_wrist", wrist)
    th_h = th + el + a[f"wrist_{side[0]}"]
    d_h = _limb_dir(th_h, be, sg, f_t, l_t, u_t)
    across = _front(th_h, f_t, u_t)  # thumb side (front when the arm hangs)
    palm = _unit(_cross(d_h, across) * sg)  # palm normal, medial when the arm hangs
    curl = a["finger_curl"]
    fingers = {
        "index": (0.026, 0.085, (0.040, 0.024, 0.020)),
        "middle": (0.008, 0.088, (0.045, 0.028, 0.022)),
        "ring": (-0.011, 0.084, (0.042, 0.026, 0.021)),
        "pinky": (-0.027, 0.077, (0.033, 0.019, 0.018)),
    }
    dirs = _phalanx_dirs(d_h, palm, curl)  # the same for the four fingers
    for name, (off, base, lengths) in fingers.items():
        p = wrist + _lin((base * s, d_h), (off * s, across))
        _finger(put, f"{side}_{name}", p, lengths, s, dirs)
    thumb_dir = _unit(_lin((0.55, d_h), (0.75, across), (0.35, palm)))
    p = wrist + _lin((0.032 * s, d_h), (0.028 * s, across), (0.012 * s, palm))
    _finger(put, f"{side}_thumb", p, (0.040, 0.032, 0.028), s, _phalanx_dirs(thumb_dir, palm, 0.6 * curl))
    put(f"{side}_hand_end", wrist + _lin((0.15 * s, d_h)))


def _phalanx_dirs(d, palm, curl) -> list[np.ndarray]:
    """Unit directions (P,3) of the three phalanges: curled by k * curl (rad) from d towards palm."""
    return [_lin((np.cos(k * curl), d), (np.sin(k * curl), palm)) for k in (1, 2, 3)]


def _finger(put, prefix, p, lengths, s, dirs) -> None:
    """Joints of one finger from its base p (P,3) m: phalanx lengths (m at 1.8 m) along dirs."""
    put(f"{prefix}_third_joint", p)
    for part, length, dk in zip(("second_joint", "first_joint", "tip"), lengths, dirs):
        p = p + _lin((length * s, dk))
        put(f"{prefix}_{part}", p)


def _leg(put, side, sg, hip, a, H, s, ex, ey, ez) -> None:
    th, be = a[f"hip_flex_{side[0]}"], a[f"hip_abd_{side[0]}"]
    kn = np.maximum(a[f"knee_{side[0]}"], 0.0)
    knee = hip + _lin((0.245 * H, _limb_dir(th, be, sg, ex, ey, ez)))
    put(f"{side}_knee", knee)
    ankle = knee + _lin((0.246 * H, _limb_dir(th - kn, be, sg, ex, ey, ez)))
    put(f"{side}_ankle", ankle)
    p = a[f"ankle_{side[0]}"]
    toe_out = 0.12 * sg
    fd = _lin((np.cos(p) * np.cos(toe_out), ex), (np.cos(p) * np.sin(toe_out), ey), (np.sin(p), ez))
    uf = _lin((-np.sin(p) * np.cos(toe_out), ex), (-np.sin(p) * np.sin(toe_out), ey), (np.cos(p), ez))
    lat = _cross(uf, fd)  # left of the foot
    Lf, ha = 0.152 * H, 0.039 * H
    put(f"{side}_heel", ankle + _lin((-0.22 * Lf, fd), (-0.85 * ha, uf)))
    big = ankle + _lin((0.76 * Lf, fd), (-0.85 * ha, uf), (-sg * 0.022 * s, lat))
    small = ankle + _lin((0.62 * Lf, fd), (-0.85 * ha, uf), (sg * 0.038 * s, lat))
    put(f"{side}_big_toe_tip", big)
    put(f"{side}_small_toe_tip", small)
    put(f"{side}_toe_mid", 0.5 * (big + small))


class BodyModel:
    """Fixed-topology surface of ``num_vertices`` vertices over PARTS (same for every person).

    part_of (V,) part index; coeff (V,4) = (1, axial position in units of the part length from
    anchor a, radial profile*cos(angle), radial profile*sin(angle)).
    """

    def __init__(self, num_vertices: int = 18439):
        if int(num_vertices) < len(PARTS):
            raise ValueError(f"num_vertices: {num_vertices} is fewer than the {len(PARTS)} body parts")
        self.num_vertices = int(num_vertices)
        counts = np.maximum(1, np.floor(part_shares() * self.num_vertices).astype(int))
        counts[np.argmax(counts)] += self.num_vertices - counts.sum()
        self.counts = counts
        self.slices = [slice(int(o), int(o + n)) for o, n in zip(np.cumsum(counts) - counts, counts)]
        self.part_of = np.repeat(np.arange(len(PARTS)), counts)
        self.anchor_a = np.array([_PT[p[1]] for p in PARTS])
        self.anchor_b = np.array([_PT[p[2]] for p in PARTS])
        self.radii = np.array([[p[3], p[4]] for p in PARTS])
        self.ref_index = np.array([REFS.index(p[5]) for p in PARTS])
        self.coeff = np.concatenate([_lattice(n, p[6]) for n, p in zip(counts, PARTS)])
        #: (V,) noise group index (into NOISE_GROUPS) of each vertex
        self.group_of = np.array([NOISE_GROUPS.index(PART_GROUP[p[0]]) for p in PARTS])[self.part_of]

    def vertices(self, skel: Skeleton, height: np.ndarray, width: np.ndarray) -> np.ndarray:
        """(P,V,3) world metres for the skeletons ``skel`` of persons with this shape."""
        M = self.part_frames(skel, height, width)
        out = np.empty((M.shape[0], self.num_vertices, 3))
        for k, sl in enumerate(self.slices):
            out[:, sl] = np.matmul(M[:, k], self.coeff[sl].T).transpose(0, 2, 1)
        return out

    def vertices_subset(
        self, skel: Skeleton, height: np.ndarray, width: np.ndarray, index: np.ndarray
    ) -> np.ndarray:
        """(P,len(index),3) world metres of the vertices ``index`` (sorted) only (same per-part
        products as ``vertices``)."""
        M = self.part_frames(skel, height, width)
        index = np.asarray(index)
        parts = self.part_of[index]
        out = np.empty((M.shape[0], len(index), 3))
        for k in np.unique(parts):
            sel = np.flatnonzero(parts == k)
            out[:, sel] = np.matmul(M[:, k], self.coeff[index[sel]].T).transpose(0, 2, 1)
        return out

    def part_frames(self, skel: Skeleton, height: np.ndarray, width: np.ndarray) -> np.ndarray:
        """(P,K,3,4) per-part affine maps, metres: vertex = M[p, part] @ coeff[vertex].

        Columns: anchor a, axis a -> b, e1 x radius 1, e2 x radius 2 (world frame).
        """
        pts, refs = skel.points, skel.refs
        A, B = pts[:, self.anchor_a], pts[:, self.anchor_b]  # (P,K,3)
        axis = B - A
        u = _unit(axis)
        ref = refs[:, self.ref_index]
        e1 = _unit(ref - np.sum(ref * u, -1, keepdims=True) * u)
        e2 = _cross(u, e1)
        scale = (np.asarray(width, float) * np.asarray(height, float) / 1.8)[:, None, None]
        r = self.radii[None] * scale  # (P,K,2)
        return np.stack([A, axis, e1 * r[..., :1], e2 * r[..., 1:]], axis=-1)  # (P,K,3,4)

    def evaluate_components(self, M: np.ndarray) -> np.ndarray:
        """(P,3,V) coordinates, component-major, of the vertices under part maps M (P,K,3,4)
        (e.g. ``part_frames`` moved into a camera frame): out[:, c] is contiguous per component."""
        out = np.empty((M.shape[0], 3, self.num_vertices))
        for k, sl in enumerate(self.slices):
            np.matmul(M[:, k], self.coeff[sl].T, out=out[:, :, sl])
        return out

    def part_vertex_sample(self, per_part: int) -> np.ndarray:
        """Indices of up to ``per_part`` evenly spread vertices of each part (for hulls/visibility)."""
        idx = [
            np.linspace(sl.start, sl.stop - 1, min(per_part, sl.stop - sl.start)).round().astype(int)
            for sl in self.slices
        ]
        return np.concatenate(idx)


def part_shares() -> np.ndarray:
    """(K,) fraction of the vertices on each part: PART_SHARE, the rest by template area."""
    area = np.array([_template_area(p) for p in PARTS])
    fixed = np.array([PART_SHARE.get(p[0], np.nan) for p in PARTS])
    free = np.isnan(fixed)
    out = fixed.copy()
    out[free] = area[free] / area[free].sum() * (1.0 - np.nansum(fixed))
    return out


def _template_area(part) -> float:
    """Approximate surface area (m^2) of a part of the 1.8 m template: allots the vertices."""
    pi = np.pi
    lengths = {
        "head": 0.22,
        "neck": 0.07,
        "chest": 0.3,
        "abdomen": 0.25,
        "pelvis": 0.18,
        "upper_arm_l": 0.33,
        "upper_arm_r": 0.33,
        "forearm_l": 0.26,
        "forearm_r": 0.26,
        "hand_l": 0.19,
        "hand_r": 0.19,
        "thigh_l": 0.44,
        "thigh_r": 0.44,
        "shin_l": 0.44,
        "shin_r": 0.44,
        "foot_l": 0.25,
        "foot_r": 0.25,
        "shoulders": 0.38,
        "hips_band": 0.18,
    }
    name, _, _, r1, r2, _, ext = part
    return pi * (r1 + r2) * lengths[name] * (1 + 2 * ext) + 2 * pi * r1 * r2


def _lattice(n: int, ext: float) -> np.ndarray:
    """(n,4) Fibonacci-lattice coefficients on a rounded cylinder (superellipse profile)."""
    i = np.arange(n) + 0.5
    t = i / n  # 0..1 along the rounded body
    phi = 2.0 * np.pi * ((i * 0.6180339887498949) % 1.0)
    axial = t * (1.0 + 2.0 * ext) - ext
    u = 2.0 * t - 1.0
    prof = (1.0 - np.abs(u) ** 4) ** 0.25
    return np.stack([np.ones(n), axial, prof * np.cos(phi), prof * np.sin(phi)], axis=1)


def gait_angles(
    speed: np.ndarray,
    phase: np.ndarray,
    crouch: np.ndarray,
    arm_raise: np.ndarray,
    head_yaw: np.ndarray,
    twist: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Joint angles (rad) of a running/standing/crouching/reaching pose.

    speed (P,) m/s; phase (P,) rad of the stride cycle; crouch, arm_raise (P,) 0..1; head_yaw (P,) rad.
    """
    v = np.asarray(speed, dtype=np.float64)
    amp = np.clip(v / 6.0, 0.0, 1.0) * (0.55 + 0.45 * np.clip(v / 3.0, 0.0, 1.0))
    c, r = np.clip(crouch, 0.0, 1.0), np.clip(arm_raise, 0.0, 1.0)
    sp, cp = np.sin(phase), np.cos(phase)
    swing_l = 0.5 + 0.5 * cp
    swing_r = 0.5 - 0.5 * cp
    zeros = np.zeros_like(v)
    return {
        "lean": 0.04 + 0.22 * amp + 0.28 * c,
        "side_lean": 0.03 * amp * sp,
        "twist": (0.12 * amp * sp) if twist is None else twist,
        "head_yaw": np.asarray(head_yaw, dtype=np.float64),
        "head_pitch": 0.05 - 0.2 * amp - 0.2 * c,
        "hip_flex_l": 0.75 * amp * sp + 0.55 * c,
        "hip_flex_r": -0.75 * amp * sp + 0.55 * c,
        "hip_abd_l": 0.04 + 0.1 * c,
        "hip_abd_r": 0.04 + 0.1 * c,
        "knee_l": 0.08 + 0.95 * c + amp * (0.25 + 1.1 * swing_l**2),
        "knee_r": 0.08 + 0.95 * c + amp * (0.25 + 1.1 * swing_r**2),
        "ankle_l": 0.25 * amp * sp,
        "ankle_r": -0.25 * amp * sp,
        "sh_flex_l": (1 - r) * (-0.8 * amp * sp + 0.2 * c) + r * 2.7,
        "sh_flex_r": (1 - r) * (0.8 * amp * sp + 0.2 * c) + r * 2.6,
        "sh_abd_l": 0.12 + 0.15 * c + 0.1 * r,
        "sh_abd_r": 0.12 + 0.15 * c + 0.1 * r,
        "elbow_l": (1 - r) * (0.25 + 1.1 * amp + 0.5 * c) + r * 0.15,
        "elbow_r": (1 - r) * (0.25 + 1.1 * amp + 0.5 * c) + r * 0.2,
        "wrist_l": 0.1 + zeros,
        "wrist_r": 0.1 + zeros,
        "finger_curl": 0.3 + 0.2 * (1 - r) + zeros,
    }
