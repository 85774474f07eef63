"""Levenberg-Marquardt internals of :mod:`.bundle`: state, projection with an analytic Jacobian,
normal equations and their Schur complement.

Layout of the normal equations: camera blocks (C, dc, dc) with dc = 6 (rotation perturbation,
translation) + optional focal scale + optional k1; structure blocks of two groups, free points
(3x3) and rigid objects (6x6, rotation perturbation and translation of the object pose). The
structure is eliminated (it is block-diagonal); the reduced camera system (C dc)^2 is solved
densely. Observations are processed in chunks, and each group's Schur product is formed as
dense (C dc, chunk) x (chunk, C dc) matrix products: small temporaries that are reused, BLAS
for the bulk of the arithmetic, no Python loop over observations or points.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

MIN_DEPTH = 1e-3  # m: points nearer than this to (or behind) a camera project as if at it
_CHUNK = 16384  # observations per vectorised pass
_STRUCT_CHUNK = 2048  # structure blocks per dense Schur product


def robust_rho(loss: str, s: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """(rho(s), rho'(s)) of a squared residual norm s (px^2) for a loss of scale c px; rho is
    normalised so that rho(s) ~ s for s << c^2."""
    z = s / (c * c)
    if loss == "linear":
        return s, np.ones_like(s)
    if loss == "cauchy":
        return c * c * np.log1p(z), 1.0 / (1.0 + z)
    if loss == "soft_l1":
        root = np.sqrt(1.0 + z)
        return 2.0 * c * c * (root - 1.0), 1.0 / root
    if loss == "huber":
        small = z <= 1.0
        root = np.sqrt(np.maximum(s, 1e-300))
        return np.where(small, s, 2.0 * c * root - c * c), np.where(small, 1.0, c / root)
    raise ValueError(f"bundle options: unknown robust loss {loss!r} (linear, cauchy, soft_l1, huber)")


def skew(v: np.ndarray) -> np.ndarray:
    """(...,3) -> (...,3,3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


class State:
    """The unknowns: cameras R (C,3,3), t (C,3), focal scale s (C,), k1 (C,); free points X
    (P,3); object poses oR (O,3,3), ot (O,3). Camera block = [rotation 3, t 3, (s), (k1)]."""

    def __init__(self, R, t, s, k1, X, oR, ot, refine_focal: bool, refine_k1: bool):
        self.R, self.t, self.s, self.k1 = R.copy(), t.copy(), s.copy(), k1.copy()
        self.X, self.oR, self.ot = X.copy(), oR.copy(), ot.copy()
        self.refine_focal, self.refine_k1 = refine_focal, refine_k1
        self.dc = 6 + int(refine_focal) + int(refine_k1)

    def updated(self, dcam: np.ndarray, dpt: np.ndarray, dobj: np.ndarray) -> State:
        """State after a step: cameras (C,dc), free points (P,3), objects (O,6); rotations are
        perturbed on the left, R <- exp([d]x) R."""
        R = Rotation.from_rotvec(dcam[:, :3]).as_matrix() @ self.R
        s, k1, col = self.s, self.k1, 6
        if self.refine_focal:
            s, col = self.s + dcam[:, col], col + 1
        if self.refine_k1:
            k1 = self.k1 + dcam[:, col]
        oR, ot = self.oR, self.ot
        if len(oR):
            oR = Rotation.from_rotvec(dobj[:, :3]).as_matrix() @ self.oR
            ot = self.ot + dobj[:, 3:]
        return State(R, self.t + dcam[:, 3:6], s, k1, self.X + dpt, oR, ot,
                     self.refine_focal, self.refine_k1)


class Observations:
    """Active observations ordered for the solver: free-point ones sorted by (point, camera),
    then rigid ones sorted by (object, camera). ``idx`` maps back to the problem's order."""

    def __init__(self, prob, active: np.ndarray):
        idx = np.flatnonzero(active)
        obj = prob.point_object[prob.obs_point[idx]]
        C = prob.num_cameras
        key = np.where(obj < 0, prob.obs_point[idx], prob.points.shape[0] + obj) * C \
            + prob.obs_camera[idx]
        self.idx = idx[np.argsort(key, kind="stable")]
        self.cam = prob.obs_camera[self.idx]
        self.pt = prob.obs_point[self.idx]
        self.uv = prob.obs_uv[self.idx]
        self.w = prob.obs_weight[self.idx]
        self.obj = prob.point_object[self.pt]
        self.model = prob.model[self.pt]
        self.K2 = prob.K[:, :2, :2]
        self.c0 = prob.K[:, :2, 2]
        self.n_free = int(np.count_nonzero(self.obj < 0))
        self.points, self.point_key = np.unique(self.pt[:self.n_free], return_inverse=True)
        self.objects, self.object_key = np.unique(self.obj[self.n_free:], return_inverse=True)
        self.point_key, self.object_key = self.point_key.ravel(), self.object_key.ravel()

    def __len__(self) -> int:
        return int(self.idx.size)

    def chunks(self):
        for a in range(0, len(self), _CHUNK):
            yield slice(a, min(a + _CHUNK, len(self)))


def project(st: State, ob: Observations, sl: slice, jac: bool):
    """Residuals (k,2) px (projection - observation) of the observations ``sl``; with ``jac``
    also the Jacobians w.r.t. the camera block (k,2,dc) and the structure block (k,2,3) for
    free points / (k,2,6) for rigid objects (the slice's first and second part)."""
    cam, pt, obj = ob.cam[sl], ob.pt[sl], ob.obj[sl]
    rigid = obj >= 0
    X = st.X[pt]
    RoM = None
    if rigid.any():
        RoM = np.einsum("nij,nj->ni", st.oR[obj[rigid]], ob.model[sl][rigid])
        X[rigid] = RoM + st.ot[obj[rigid]]
    Rc = st.R[cam]
    RX = np.einsum("nij,nj->ni", Rc, X)
    Xc = RX + st.t[cam]
    z = np.maximum(Xc[:, 2], MIN_DEPTH)
    xn = Xc[:, :2] / z[:, None]
    r2 = np.einsum("ni,ni->n", xn, xn)
    k1, s = st.k1[cam], st.s[cam]
    d = 1.0 + k1 * r2
    A2 = ob.K2[cam] * s[:, None, None]
    res = np.einsum("nij,nj->ni", A2, xn * d[:, None]) + ob.c0[cam] - ob.uv[sl]
    if not jac:
        return res
    m = res.shape[0]
    # d u / d Xc = A2 (d I + 2 k1 xn xn^T) d xn / d Xc, written out per entry (2x2 and 2x3
    # products of many tiny matrices are far slower as batched matmuls)
    a_, b_ = xn[:, 0], xn[:, 1]
    M00, M01, M11 = d + 2 * k1 * a_ * a_, 2 * k1 * a_ * b_, d + 2 * k1 * b_ * b_
    A00, A01, A11 = A2[:, 0, 0], A2[:, 0, 1], A2[:, 1, 1]
    P = np.empty((m, 2, 2))
    P[:, 0, 0], P[:, 0, 1] = A00 * M00 + A01 * M01, A00 * M01 + A01 * M11
    P[:, 1, 0], P[:, 1, 1] = A11 * M01, A11 * M11
    inv_z = np.where(Xc[:, 2] < MIN_DEPTH, 0.0, 1.0 / z)
    D = np.empty((m, 2, 3))
    D[:, :, :2] = P * inv_z[:, None, None]
    D[:, :, 2] = -(P[:, :, 0] * a_[:, None] + P[:, :, 1] * b_[:, None]) * inv_z[:, None]
    Jc = np.empty((m, 2, st.dc))
    Jc[:, :, :3] = np.cross(RX[:, None, :], D)  # -D [RX]x, row-wise RX x D_i
    Jc[:, :, 3:6] = D
    col = 6
    if st.refine_focal:
        Jc[:, :, col] = np.einsum("nij,nj->ni", ob.K2[cam], xn * d[:, None])
        col += 1
    if st.refine_k1:
        Jc[:, :, col] = np.einsum("nij,nj->ni", A2, xn * r2[:, None])
    dudX = D[:, :, 0, None] * Rc[:, None, 0, :] + D[:, :, 1, None] * Rc[:, None, 1, :] \
        + D[:, :, 2, None] * Rc[:, None, 2, :]
    Jp = dudX[~rigid]
    Jo = np.zeros((int(rigid.sum()), 2, 6))
    if RoM is not None:
        Jo[:, :, :3] = np.cross(RoM[:, None, :], dudX[rigid])
        Jo[:, :, 3:] = dudX[rigid]
    return res, Jc, Jp, Jo


def outer_sum(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(k,r,a), (k,r,b) -> (k,a,b) = sum_r A[:, r, :, None] B[:, r, None, :] (A^T B per row)."""
    out = A[:, 0, :, None] * B[:, 0, None, :]
    for r in range(1, A.shape[1]):
        out += A[:, r, :, None] * B[:, r, None, :]
    return out


def batched_matvec_blocks(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(k,a,c), (k,c,b) -> (k,a,b) = A B per row, summed over the small inner dimension."""
    out = A[:, :, 0, None] * B[:, None, 0, :]
    for r in range(1, A.shape[2]):
        out += A[:, :, r, None] * B[:, None, r, :]
    return out


def block_sum(keys: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum (m,a,b) or (m,a) blocks into (n,a,b) / (n,a) by key (one bincount per entry)."""
    shape = values.shape[1:]
    flat = values.reshape(values.shape[0], -1)
    out = np.empty((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.bincount(keys, weights=flat[:, k], minlength=n)
    return out.reshape((n,) + shape)


class Group:
    """One structure group's normal-equation pieces: V (n,ds,ds), gradient gs (n,ds), and the
    camera coupling W (rows,dc,ds) of each (structure, camera) row, rows sorted by structure."""

    def __init__(self, n: int, ds: int, dc: int, rows_cam: np.ndarray, rows_struct: np.ndarray):
        self.V = np.zeros((n, ds, ds))
        self.gs = np.zeros((n, ds))
        self.W = np.zeros((rows_cam.size, dc, ds))
        self.cam, self.struct = rows_cam, rows_struct
        bounds = np.searchsorted(rows_struct, np.arange(0, n + _STRUCT_CHUNK, _STRUCT_CHUNK))
        self.chunks = [(int(bounds[i]), int(bounds[i + 1]), i * _STRUCT_CHUNK,
                        min(n, (i + 1) * _STRUCT_CHUNK)) for i in range(len(bounds) - 1)
                       if bounds[i + 1] > bounds[i]]


class NormalEquations:
    """J^T W J and J^T W r of the robustified problem at one state (IRLS weights)."""

    def __init__(self, st: State, ob: Observations, loss: str, scale: float, C: int):
        dc = st.dc
        self.U = np.zeros((C, dc, dc))
        self.gc = np.zeros((C, dc))
        nf = ob.n_free
        self.free = Group(ob.points.size, 3, dc, ob.cam[:nf], ob.point_key)
        obj_pairs, self._pair_of_obs = np.unique(ob.object_key * C + ob.cam[nf:], return_inverse=True)
        self._pair_of_obs = self._pair_of_obs.ravel()
        self.rigid = Group(ob.objects.size, 6, dc, obj_pairs % C, obj_pairs // C)
        for sl in ob.chunks():
            self._add(st, ob, sl, loss, scale, C)

    def _add(self, st: State, ob: Observations, sl: slice, loss: str, scale: float, C: int) -> None:
        res, Jc, Jp, Jo = project(st, ob, sl, True)
        w = robust_rho(loss, np.einsum("ni,ni->n", res, res), scale)[1] * ob.w[sl]
        cam = ob.cam[sl]
        Jc_w = Jc * w[:, None, None]
        dc = st.dc
        for c in np.unique(cam):
            on = cam == c
            self.U[c] += Jc_w[on].reshape(-1, dc).T @ Jc[on].reshape(-1, dc)
        self.gc += block_sum(cam, np.einsum("nki,nk->ni", Jc_w, res), C)
        nf = ob.n_free
        fr = slice(sl.start, min(sl.stop, nf))
        k = max(0, fr.stop - fr.start)
        if k:
            self._add_group(self.free, ob.point_key[fr], Jc_w[:k], Jp, w[:k], res[:k])
            self.free.W[fr] = outer_sum(Jc_w[:k], Jp)
        if k < res.shape[0]:
            rows = self._pair_of_obs[max(sl.start, nf) - nf:sl.stop - nf]
            self._add_group(self.rigid, self.rigid.struct[rows], Jc_w[k:], Jo, w[k:], res[k:])
            self.rigid.W += block_sum(rows, outer_sum(Jc_w[k:], Jo),
                                      self.rigid.W.shape[0])

    @staticmethod
    def _add_group(g: Group, keys, Jc_w, Js, w, res) -> None:
        Js_w = Js * w[:, None, None]
        n = g.V.shape[0]
        g.V += block_sum(keys, outer_sum(Js_w, Js), n)
        g.gs += block_sum(keys, np.einsum("nki,nk->ni", Js_w, res), n)


def damp(A: np.ndarray, mu: float) -> np.ndarray:
    """A + mu diag(A) blockwise (Marquardt), the diagonal clamped away from 0."""
    diag = np.clip(np.diagonal(A, axis1=-2, axis2=-1), 1e-6, 1e32)
    return A + mu * diag[..., :, None] * np.eye(A.shape[-1])


def reduced_system(ne: NormalEquations, mu: float, free_cam: np.ndarray):
    """(S (C dc, C dc), rhs (C dc,), V^-1 per group) of the damped system after eliminating
    the structure; fixed cameras get identity rows. None if a structure block is singular."""
    C, dc, _ = ne.U.shape
    Ud = damp(ne.U, mu)
    S = np.zeros((C * dc, C * dc))
    for c in range(C):
        S[c * dc:(c + 1) * dc, c * dc:(c + 1) * dc] = Ud[c]
    rhs = -ne.gc.ravel().copy()
    inverses = []
    for g in (ne.free, ne.rigid):
        if g.V.shape[0] == 0:
            inverses.append(g.V)
            continue
        try:
            Vinv = np.linalg.inv(damp(g.V, mu))
        except np.linalg.LinAlgError:
            return None
        inverses.append(Vinv)
        ds = g.V.shape[1]
        for r0, r1, s0, s1 in g.chunks:
            W = g.W[r0:r1]
            Y = batched_matvec_blocks(W, Vinv[g.struct[r0:r1]])
            Yd = np.zeros((C, dc, s1 - s0, ds))
            Wd = np.zeros((C, dc, s1 - s0, ds))
            Yd[g.cam[r0:r1], :, g.struct[r0:r1] - s0, :] = Y
            Wd[g.cam[r0:r1], :, g.struct[r0:r1] - s0, :] = W
            Yf = Yd.reshape(C * dc, -1)
            S -= Yf @ Wd.reshape(C * dc, -1).T
            rhs += Yf @ g.gs[s0:s1].ravel()
    fixed = np.repeat(~free_cam, dc)
    S[fixed] = 0.0
    S[:, fixed] = 0.0
    S[fixed, fixed] = 1.0
    rhs[fixed] = 0.0
    return S, rhs, inverses


def solve_step(ne: NormalEquations, mu: float, free_cam: np.ndarray):
    """The damped LM step: cameras (C,dc), free points (n,3), objects (n,6); None if singular."""
    red = reduced_system(ne, mu, free_cam)
    if red is None:
        return None
    S, rhs, inverses = red
    C, dc, _ = ne.U.shape
    try:
        dcam = np.linalg.solve(S, rhs).reshape(C, dc)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(dcam)):
        return None
    steps = []
    for g, Vinv in zip((ne.free, ne.rigid), inverses):
        n = g.V.shape[0]
        if n == 0:
            steps.append(np.zeros((0, g.V.shape[1])))
            continue
        WT_dc = block_sum(g.struct, np.einsum("rji,rj->ri", g.W, dcam[g.cam]), n)
        steps.append(-np.einsum("nij,nj->ni", Vinv, g.gs + WT_dc))
    return dcam, steps[0], steps[1]
