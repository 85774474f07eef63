"""Simulated frame sets: people as ellipsoid bodies (V mesh vertices, J keypoints, one fixed
topology per template, per-person pose jitter carried to the vertices by nearest-keypoint
skinning) standing on a court, projected through a calibrated rig into RAW (distorted) px plus
pixel noise, and the rectified FrameDetections a frontend would publish of them.

Two users: maem-bench's standard load (``players`` people seen by every camera plus ``extras``
per camera seen by that camera only), and the nodes' start-up warm passes, which run their own
path on a few of these frame sets before the first real one arrives (so a real stream never pays
first-call costs). World frame: the rig's (metres, z up, court centre at the origin).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig

#: half-extent of the court area players stand on (world x, y metres; court 28 x 15 m)
COURT_HALF = (13.0, 6.5)


@dataclass
class RawDetections:
    """One camera's detections in RAW px, as a detector on the distorted image gives them."""

    bboxes: np.ndarray  # (N,4) raw px
    scores: np.ndarray  # (N,)
    verts: np.ndarray  # (N,V,2) raw px
    kpts3d: np.ndarray  # (N,J,3) camera-relative, root-relative metres


@dataclass
class BenchFrame:
    frames: dict[str, FrameDetections]  # rectified, for the fast path
    raw: dict[str, RawDetections]  # raw px, for the straightforward path
    truth: list[frozenset]  # true player clusters: sets of (camera index, detection index)


# ---------------------------------------------------------------------------------------
# synthetic bodies
# ---------------------------------------------------------------------------------------
#: body parts as ellipsoids: centre (x, y, z) m, radii m (person faces +x, z up)
_PARTS = np.array(
    [
        [0.0, 0.0, 1.65, 0.10, 0.09, 0.12],  # head
        [0.0, 0.0, 1.20, 0.13, 0.20, 0.30],  # torso
        [0.0, 0.28, 1.15, 0.06, 0.06, 0.33],  # left arm
        [0.0, -0.28, 1.15, 0.06, 0.06, 0.33],  # right arm
        [0.0, 0.10, 0.45, 0.08, 0.08, 0.45],  # left leg
        [0.0, -0.10, 0.45, 0.08, 0.08, 0.45],  # right leg
    ]
)


def body_template(
    num_vertices: int, num_joints: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(verts (V,3), joints (J,3), attach (V,) nearest joint of each vertex), metres.

    Vertices on the surface of six ellipsoids, joints inside the body; a fixed topology.
    """
    rng = np.random.default_rng(seed)
    area = np.prod(_PARTS[:, 3:], axis=1) ** (2 / 3)
    part = rng.choice(len(_PARTS), size=num_vertices, p=area / area.sum())
    d = rng.normal(size=(num_vertices, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    verts = _PARTS[part, :3] + d * _PARTS[part, 3:]
    jpart = rng.choice(len(_PARTS), size=num_joints)
    joints = _PARTS[jpart, :3] + rng.uniform(-0.8, 0.8, (num_joints, 3)) * _PARTS[jpart, 3:]
    attach = np.argmin(((verts[:, None, :] - joints[None]) ** 2).sum(-1), axis=1)
    return verts, joints, attach


def _yaw(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _person(template, rng) -> tuple[np.ndarray, np.ndarray]:
    """(verts (V,3), joints (J,3)) of one person at the origin: scale, yaw, pose jitter."""
    verts, joints, attach = template
    jitter = rng.normal(0.0, 0.04, joints.shape)
    R = _yaw(rng.uniform(0, 2 * np.pi)) * rng.uniform(0.9, 1.1)
    return (verts + jitter[attach]) @ R.T, (joints + jitter) @ R.T


def _in_view(cam: Camera, X: np.ndarray, margin: float = 40.0) -> bool:
    """Every point of X (P,3) world m in front of ``cam`` and inside its image, ``margin`` px in."""
    if np.any(cam.world_to_camera(X)[:, 2] <= 0):
        return False
    uv = cam.project(X)
    hi = np.array([cam.width, cam.height]) - margin
    return bool(np.all(np.isfinite(uv)) and np.all(uv >= margin) and np.all(uv <= hi))


#: where people stand: floor centre (world x, y m) and half-extents (m); the default is the court
Area = tuple[tuple[float, float], tuple[float, float]]
COURT: Area = ((0.0, 0.0), COURT_HALF)


def _place(
    rig_cams: list[Camera],
    rng,
    taken: list[np.ndarray],
    area: Area = COURT,
    tries: int = 10000,
    min_sep: float = 1.0,
) -> np.ndarray:
    """A floor position (x, y, 0) in ``area`` whose body box is in view of every camera in rig_cams."""
    box = np.array([[dx, dy, z] for dx in (-0.3, 0.3) for dy in (-0.3, 0.3) for z in (0.0, 1.8)])
    (cx, cy), (hx, hy) = area
    for _ in range(tries):
        p = np.array([cx + rng.uniform(-hx, hx), cy + rng.uniform(-hy, hy), 0.0])
        if any(np.linalg.norm(p - q) < min_sep for q in taken):
            continue
        if all(_in_view(c, box + p) for c in rig_cams):
            taken.append(p)
            return p
    raise ValueError(f"synthetic load: cannot place a person in view of the required cameras ({tries} tries)")


def _detect(
    cam: Camera, verts: np.ndarray, joints: np.ndarray, rng, px_noise: float
) -> tuple[np.ndarray, ...]:
    """One detection of a world-space body: raw bbox, rectified bbox, raw verts, rectified
    verts, rectified kpts2d, kpts3d (camera-relative, root-relative metres)."""
    raw_v = cam.project(verts) + rng.normal(0.0, px_noise, (len(verts), 2))
    raw_box = np.concatenate([raw_v.min(0), raw_v.max(0)])
    centre = cam.undistort_points(0.5 * (raw_box[:2] + raw_box[2:]))
    half = 0.5 * (raw_box[2:] - raw_box[:2])
    rect_box = np.concatenate([centre - half, centre + half])
    rect_v = cam.undistort_points(raw_v)
    kp2d = cam.undistort_points(cam.project(joints) + rng.normal(0.0, px_noise, (len(joints), 2)))
    kp3d = cam.world_to_camera(joints)
    kp3d = kp3d - kp3d[0] + rng.normal(0.0, 0.01, kp3d.shape)
    return raw_box, rect_box, raw_v, rect_v, kp2d, kp3d


def make_frame(
    rig: Rig,
    template,
    rng: np.random.Generator,
    players: int = 10,
    extras: int = 2,
    px_noise: float = 0.5,
    stamp_ns: int = 0,
) -> BenchFrame:
    """One frame of the standard load (detection order within a camera is shuffled)."""
    return _detect_people(rig, _people(rig, template, rng, players, extras), rng, px_noise, stamp_ns, players)


def make_sequence(
    rig: Rig,
    template,
    rng: np.random.Generator,
    players: int = 10,
    extras: int = 2,
    frames: int = 30,
    fps: float = 30.0,
    px_noise: float = 0.5,
    speed: float = 1.5,
    area: Area = COURT,
    tries: int = 10000,
) -> list[BenchFrame]:
    """The standard load in motion: the same people (placed as in make_frame) walking at
    ``speed`` m/s in random directions for ``frames`` frames at ``fps`` (the temporal bench).
    People stand in ``area``; placing one takes at most ``tries`` draws (else ValueError)."""
    people = _people(rig, template, rng, players, extras, area, tries)
    heading = rng.uniform(0, 2 * np.pi, len(people))
    vel = speed * np.stack([np.cos(heading), np.sin(heading), np.zeros(len(people))], axis=1)
    out = []
    for f in range(frames):
        shift = vel * f / fps  # (persons, 3)
        moved = [(v + d, j + d, cams, player) for (v, j, cams, player), d in zip(people, shift)]
        out.append(_detect_people(rig, moved, rng, px_noise, int(round(f * 1e9 / fps)), players))
    return out


def _people(
    rig: Rig,
    template,
    rng: np.random.Generator,
    players: int,
    extras: int,
    area: Area = COURT,
    tries: int = 10000,
) -> list:
    """(verts, joints, camera indices that see it, is player) per person, players first."""
    cams = rig.cameras
    taken: list[np.ndarray] = []
    people: list[tuple[np.ndarray, np.ndarray, Sequence[int], bool]] = []
    for _ in range(players):
        v, j = _person(template, rng)
        p = _place(cams, rng, taken, area, tries)
        people.append((v + p, j + p, range(len(cams)), True))
    for c in range(len(cams)):
        for _ in range(extras):
            v, j = _person(template, rng)
            p = _place([cams[c]], rng, taken, area, tries)
            people.append((v + p, j + p, [c], False))
    return people


def _detect_people(
    rig: Rig, people: list, rng: np.random.Generator, px_noise: float, stamp_ns: int, players: int
) -> BenchFrame:
    """Every camera's detections of ``people`` (shuffled order) and the true player clusters."""
    truth: dict[int, set[tuple[int, int]]]
    frames, raw, truth = {}, {}, {k: set() for k in range(players)}
    for c, cam in enumerate(rig.cameras):
        seen = [k for k, person in enumerate(people) if c in person[2]]
        order = rng.permutation(len(seen))
        dets = [_detect(cam, people[seen[o]][0], people[seen[o]][1], rng, px_noise) for o in order]
        for d_idx, o in enumerate(order):
            if people[seen[o]][3]:
                truth[seen[o]].add((c, d_idx))
        scores = rng.uniform(0.92, 1.0, len(dets))
        frames[cam.name] = FrameDetections(
            cam.name,
            stamp_ns,
            np.array([d[1] for d in dets]),
            scores,
            np.array([d[4] for d in dets]),
            np.array([d[5] for d in dets]),
            np.array([d[3] for d in dets], dtype=np.float32),
        )
        raw[cam.name] = RawDetections(
            np.array([d[0] for d in dets]),
            scores,
            np.array([d[2] for d in dets]),
            np.array([d[5] for d in dets]),
        )
    return BenchFrame(frames, raw, [frozenset(s) for s in truth.values()])


def rig_focus(rig: Rig) -> np.ndarray:
    """The world point (m) nearest to every camera's optical axis in the least-squares sense:
    where a rig that surrounds a scene looks (the court centre at player height for a court rig)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in rig.cameras:  # a handful of cameras: one 3x3 sum each
        axis = cam.R[2]  # the optical axis in world coordinates (third row of world-to-camera R)
        off_axis = np.eye(3) - np.outer(axis, axis)
        A += off_axis
        b += off_axis @ cam.center
    return np.asarray(np.linalg.lstsq(A, b, rcond=None)[0])


def warm_sequence(
    rig: Rig, frames: int = 2, players: int = 4, vertices: int = 9000, keypoints: int = 70, seed: int = 0
) -> list[BenchFrame]:
    """A few frame sets for a node's start-up warm pass: up to ``players`` people (fewer where the
    cameras' shared view is small) within 2 m of where the rig looks (rig_focus), each seen by
    every camera, walking for ``frames`` frames (>= 2 runs a track stage's track-assisted path).
    ``vertices`` above two of the epipolar kernel's 4096-point blocks gives a subsampled mesh copy
    the block layout real meshes give. ValueError when the cameras share no view of the floor
    there (a rig whose world is not z-up, say)."""
    focus = rig_focus(rig)
    area: Area = ((float(focus[0]), float(focus[1])), (2.0, 2.0))
    template = body_template(vertices, keypoints, seed)
    for n in range(players, 0, -1):
        try:
            rng = np.random.default_rng(seed)
            return make_sequence(rig, template, rng, n, 0, frames, area=area, tries=500)
        except ValueError:
            if n == 1:
                raise
    raise ValueError("synthetic load: no people asked for")
