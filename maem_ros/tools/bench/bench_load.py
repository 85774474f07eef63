"""The maem-bench standard load and a straightforward reference association.

Load: a calibrated rig (default the shipped 6-camera ``sportcenter6``, plumb_bob distortion),
``players`` people seen by every camera plus ``extras`` people per camera seen by that camera
only. Every person is one 3D body (V mesh vertices, J keypoints, fixed topology from one
template, per-person pose jitter carried to the vertices by nearest-keypoint skinning),
projected through the rig into RAW (distorted) px plus pixel noise; the fast path gets the
rectified FrameDetections the frontend would publish, the straightforward path the raw px.

The straightforward association follows the method text literally: loops over camera pairs
and detection pairs, per-pair undistortion of the raw bbox centres and raw mesh vertices with
OpenCV, one DLT least-squares solve per pair, per-pair distance computation, per-pair SVD
Procrustes, Hungarian, union-find, conflict removal, K_min.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.association import AssociationParams
from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig, fundamental_matrix

#: half-extent of the court area players stand on (world x, y metres; court 28 x 15 m)
COURT_HALF = (13.0, 6.5)


def ring_rig(num_cameras: int = 16) -> Rig:
    """``num_cameras`` elevated cameras on an ellipse around the court, all looking at its centre
    (1920x1080, f 1000 px, mild plumb_bob distortion): every player is seen by every camera."""
    from maem_ros.sim.rigs import look_at

    cams = []
    for k in range(num_cameras):
        phi = 2 * np.pi * k / num_cameras
        eye = np.array([24.0 * np.cos(phi), 17.0 * np.sin(phi), 7.0 + 0.3 * (k % 3)])
        R, t = look_at(eye, np.array([0.0, 0.0, 0.8]))
        K = np.array([[1000.0, 0.0, 959.5 + k % 5], [0.0, 1000.0, 539.5 - k % 4], [0.0, 0.0, 1.0]])
        cams.append(
            Camera(
                name=f"camera_{k}",
                K=K,
                R=R,
                t=t,
                width=1920,
                height=1080,
                distortion_model="plumb_bob",
                D=np.array([-0.08 - 0.002 * (k % 4), 0.02, 0.0005, -0.0003, 0.0]),
            )
        )
    return Rig(cams)


def load_bench_rig(name: str) -> Rig:
    """``ring16`` (the large load's rig), or a shipped rig name / rig file."""
    if name.startswith("ring") and name[4:].isdigit():
        return ring_rig(int(name[4:]))
    from maem_ros.sim.rigs import load_rig

    return load_rig(name)


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
    uv = cam.project(X)
    hi = np.array([cam.width, cam.height]) - margin
    return bool(np.all(np.isfinite(uv)) and np.all(uv >= margin) and np.all(uv <= hi))


def _place(rig_cams: list[Camera], rng, taken: list[np.ndarray], min_sep: float = 1.0) -> np.ndarray:
    """A floor position (x, y, 0) whose body box is in view of every camera in rig_cams."""
    box = np.array([[dx, dy, z] for dx in (-0.3, 0.3) for dy in (-0.3, 0.3) for z in (0.0, 1.8)])
    for _ in range(10000):
        p = np.array(
            [rng.uniform(-COURT_HALF[0], COURT_HALF[0]), rng.uniform(-COURT_HALF[1], COURT_HALF[1]), 0.0]
        )
        if any(np.linalg.norm(p - q) < min_sep for q in taken):
            continue
        if all(_in_view(c, box + p) for c in rig_cams):
            taken.append(p)
            return p
    raise ValueError("bench load: cannot place a person in view of the required cameras")


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
) -> list[BenchFrame]:
    """The standard load in motion: the same people (placed as in make_frame) walking at
    ``speed`` m/s in random directions for ``frames`` frames at ``fps`` (the temporal bench)."""
    people = _people(rig, template, rng, players, extras)
    heading = rng.uniform(0, 2 * np.pi, len(people))
    vel = speed * np.stack([np.cos(heading), np.sin(heading), np.zeros(len(people))], axis=1)
    out = []
    for f in range(frames):
        shift = vel * f / fps  # (persons, 3)
        moved = [(v + d, j + d, cams, player) for (v, j, cams, player), d in zip(people, shift)]
        out.append(_detect_people(rig, moved, rng, px_noise, int(round(f * 1e9 / fps)), players))
    return out


def _people(rig: Rig, template, rng: np.random.Generator, players: int, extras: int) -> list:
    """(verts, joints, camera indices that see it, is player) per person, players first."""
    cams = rig.cameras
    taken: list[np.ndarray] = []
    people: list[tuple[np.ndarray, np.ndarray, Sequence[int], bool]] = []
    for _ in range(players):
        v, j = _person(template, rng)
        p = _place(cams, rng, taken)
        people.append((v + p, j + p, range(len(cams)), True))
    for c in range(len(cams)):
        for _ in range(extras):
            v, j = _person(template, rng)
            p = _place([cams[c]], rng, taken)
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


# ---------------------------------------------------------------------------------------
# straightforward reference association (written the way the method reads)
# ---------------------------------------------------------------------------------------
def _dlt_two(Pa: np.ndarray, Pb: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Inhomogeneous DLT of one point seen in two views (least squares, X4 = 1)."""
    A = np.array([xa[0] * Pa[2] - Pa[0], xa[1] * Pa[2] - Pa[1], xb[0] * Pb[2] - Pb[0], xb[1] * Pb[2] - Pb[1]])
    return np.linalg.lstsq(A[:, :3], -A[:, 3], rcond=None)[0]


def _reproj(P: np.ndarray, X: np.ndarray, x: np.ndarray) -> float:
    h = P @ np.append(X, 1.0)
    if not h[2] > 0:
        return np.inf
    return float(np.hypot(h[0] / h[2] - x[0], h[1] / h[2] - x[1]))


def _mesh_distance(F: np.ndarray, va: np.ndarray, vb: np.ndarray, symmetric: bool) -> float:
    """Mean point-to-epipolar-line distance (px) of corresponding points va, vb (n,2)."""
    ha = np.hstack([va, np.ones((len(va), 1))])
    hb = np.hstack([vb, np.ones((len(vb), 1))])
    la = ha @ F.T  # epipolar lines of a's points in b
    e = np.abs(np.sum(la * hb, axis=1))
    d = e / np.hypot(la[:, 0], la[:, 1])
    if symmetric:
        lb = hb @ F  # epipolar lines of b's points in a
        d = 0.5 * (d + e / np.hypot(lb[:, 0], lb[:, 1]))
    return float(np.mean(d))


def pa_mpjpe_one(X: np.ndarray, Y: np.ndarray) -> float:
    """PA-MPJPE (m) of X (J,3) similarity-aligned onto Y (J,3), one SVD."""
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    U, S, Vt = np.linalg.svd(Yc.T @ Xc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / np.sum(Xc**2)
    return float(np.mean(np.linalg.norm(s * Xc @ R.T - Yc, axis=1)))


def straightforward_associate(
    rig: Rig, raw: dict[str, RawDetections], params: AssociationParams
) -> list[np.ndarray]:
    """Reference MAEM association; returns clusters as (M,2) (camera index, detection) arrays,
    sorted like core.association.pipeline.associate's."""
    names = [n for n in rig.names if n in raw]
    sub = None
    edges = []
    for ka, a in enumerate(names):
        for b in names[ka + 1 :]:
            ca, cb, A, B = rig[a], rig[b], raw[a], raw[b]
            F = fundamental_matrix(ca, cb)
            ia = [i for i in range(len(A.scores)) if A.scores[i] >= params.tau_det]
            jb = [j for j in range(len(B.scores)) if B.scores[j] >= params.tau_det]
            cost = np.full((len(ia), len(jb)), np.inf)
            for r, i in enumerate(ia):
                for s, j in enumerate(jb):
                    xa = ca.undistort_points(0.5 * (A.bboxes[i, :2] + A.bboxes[i, 2:]))
                    xb = cb.undistort_points(0.5 * (B.bboxes[j, :2] + B.bboxes[j, 2:]))
                    X = _dlt_two(ca.P, cb.P, xa, xb)
                    errs = [_reproj(ca.P, X, xa), _reproj(cb.P, X, xb)]
                    err = np.mean(errs) if params.reproj_reduce == "mean" else np.max(errs)
                    if params.reproj_gate and not err < params.tau_reproj_bbox:
                        continue
                    if sub is None:
                        from maem_ros.core.detections import vertex_subset

                        sub = vertex_subset(A.verts.shape[1], params.vertex_stride, params.vertex_count)
                        sub = np.arange(A.verts.shape[1]) if sub is None else sub
                    va = ca.undistort_points(A.verts[i][sub])
                    vb = cb.undistort_points(B.verts[j][sub])
                    dist = _mesh_distance(F, va, vb, params.epipolar_distance == "symmetric")
                    if not dist < params.tau_mesh:
                        continue
                    cost[r, s] = pa_mpjpe_one(A.kpts3d[i], B.kpts3d[j])
            big = np.where(np.isfinite(cost), cost, 1e9)
            for r, s in zip(*linear_sum_assignment(big)):
                if np.isfinite(cost[r, s]):
                    edges.append(((rig.index(a), ia[r]), (rig.index(b), jb[s])))
    return _clusters(edges, raw, rig, params)


def _clusters(edges, raw, rig, params) -> list[np.ndarray]:
    parent: dict = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            x = parent[x]
        return x

    for u, v in edges:
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[max(ru, rv)] = min(ru, rv)
    groups: dict = {}
    for x in list(parent):
        groups.setdefault(find(x), []).append(x)
    out = []
    for members in groups.values():
        members = sorted(members)
        kp = [raw[rig.names[c]].kpts3d[d] for c, d in members]
        C = np.full((len(members), len(members)), np.nan)
        for m in range(len(members)):
            for n in range(m + 1, len(members)):
                C[m, n] = C[n, m] = pa_mpjpe_one(kp[m], kp[n])
        alive = list(range(len(members)))
        while True:
            cams = [members[m][0] for m in alive]
            dup = {c for c in cams if cams.count(c) > 1}
            if not dup:
                break
            worst, worst_cost = None, -np.inf
            for m in alive:
                if members[m][0] in dup:
                    mean = np.mean([C[m, n] for n in alive if n != m])
                    if mean > worst_cost:
                        worst, worst_cost = m, mean
            alive.remove(worst)  # type: ignore[arg-type]  # dup is not empty: a member was taken
        if len(alive) >= params.k_min:
            out.append(np.array([members[m] for m in alive], dtype=np.int64))
    return sorted(out, key=lambda m: tuple(m[0]))
