"""The maem-bench rigs and a straightforward reference association.

The standard load itself (people projected through the rig, the rectified FrameDetections a
frontend would publish and the raw px a detector sees) lives in ``maem_ros.core.synthetic``,
where the nodes' start-up warm passes take it too. Rigs: a shipped rig (default the 6-camera
``sportcenter6``, plumb_bob distortion) or ``ringN``, N cameras around the court.

The straightforward association follows the method text literally: loops over camera pairs
and detection pairs, per-pair undistortion of the raw bbox centres and raw mesh vertices with
OpenCV, one DLT least-squares solve per pair, per-pair distance computation, per-pair SVD
Procrustes, Hungarian, union-find, conflict removal, K_min.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.association import AssociationParams
from maem_ros.core.geometry.camera import Camera, Rig, fundamental_matrix
from maem_ros.core.synthetic import RawDetections


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
