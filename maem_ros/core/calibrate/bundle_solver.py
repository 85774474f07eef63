"""Levenberg-Marquardt internals of :mod:`.bundle`: state, projection with an analytic Jacobian,
normal equations and their Schur complement.

Layout of the normal equations: camera blocks (C, dc, dc) with dc = 6 (rotation perturbation,
translation) + optional focal scale + optional k1; structure blocks of two groups, free points
(3x3) and rigid objects (6x6, rotation perturbation and translation of the object pose). The
structure is eliminated (it is block-diagonal); the reduced camera system (C dc)^2 is solved
densely.

Why this layout (the hot path of every calibration): observations are processed per camera
(blocks of one camera's observations, free points first, each free point at most once), so a
block's projection uses one R, t, K (no per-observation gathers), its camera block is one
(2k, dc)^T (2k, dc) product, and its structure terms are scattered by unique keys (plain
fancy-index adds, no bincount or np.add.at). Each structure keeps its camera coupling dense,
W^T (ds, C dc), zero for cameras that do not see it: the Schur complement of a group is then
one BLAS product (ds n, C dc)^T (V^-1 W^T) over all its structures, with no scatter into
per-chunk matrices, and the back-substitution another.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

MIN_DEPTH = 1e-3  # m: points nearer than this to (or behind) a camera project as if at it
_CHUNK = 16384  # observations per vectorised pass (bounds the temporaries)
_STRUCT_CHUNK = 4096  # structures per Schur product


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
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


#: intrinsic unknowns :class:`State` can refine, in camera-block order (K entries px, plumb_bob
#: distortion coefficients of the observations' image)
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: where each lives: ("K", row, col) or ("D", index)
_INTRINSIC_AT = {
    "fx": ("K", 0, 0),
    "fy": ("K", 1, 1),
    "cx": ("K", 0, 2),
    "cy": ("K", 1, 2),
    "k1": ("D", 0),
    "k2": ("D", 1),
    "p1": ("D", 2),
    "p2": ("D", 3),
    "k3": ("D", 4),
}


class State:
    """The unknowns: cameras R (C,3,3), t (C,3), focal scale s (C,), intrinsics K (C,3,3) px
    and plumb_bob distortion D (C,5) (k1 k2 p1 p2 k3); free points X (P,3); object poses oR
    (O,3,3), ot (O,3). Camera block = [rotation 3, t 3, (s), (k1), (the ``intrinsics`` named,
    in INTRINSIC_NAMES order)]."""

    def __init__(
        self, R, t, s, K, D, X, oR, ot, refine_focal: bool, refine_k1: bool, intrinsics: tuple[str, ...] = ()
    ):
        self.R, self.t, self.s, self.K, self.D = R.copy(), t.copy(), s.copy(), K.copy(), D.copy()
        self.X, self.oR, self.ot = X.copy(), oR.copy(), ot.copy()
        self.refine_focal, self.refine_k1 = refine_focal, refine_k1
        self.intrinsics = tuple(n for n in INTRINSIC_NAMES if n in intrinsics)
        self.dc = 6 + int(refine_focal) + int(refine_k1) + len(self.intrinsics)
        # tangential / higher radial terms cost a few passes per block: skipped where all zero
        self.full_lens = bool(np.any(self.D[:, 1:]) or {"k2", "p1", "p2", "k3"} & set(self.intrinsics))

    @property
    def k1(self) -> np.ndarray:
        return self.D[:, 0]

    def updated(self, dcam: np.ndarray, dpt: np.ndarray, dobj: np.ndarray) -> State:
        """State after a step: cameras (C,dc), free points (P,3), objects (O,6); rotations are
        perturbed on the left, R <- exp([d]x) R."""
        R = Rotation.from_rotvec(dcam[:, :3]).as_matrix() @ self.R
        s, K, D, col = self.s, self.K.copy(), self.D.copy(), 6
        if self.refine_focal:
            s, col = self.s + dcam[:, col], col + 1
        if self.refine_k1:
            D[:, 0] += dcam[:, col]
            col += 1
        for name in self.intrinsics:
            at = _INTRINSIC_AT[name]
            if at[0] == "K":
                K[:, at[1], at[2]] += dcam[:, col]
            else:
                D[:, at[1]] += dcam[:, col]
            col += 1
        oR, ot = self.oR, self.ot
        if len(oR):
            oR = Rotation.from_rotvec(dobj[:, :3]).as_matrix() @ self.oR
            ot = self.ot + dobj[:, 3:]
        return State(
            R,
            self.t + dcam[:, 3:6],
            s,
            K,
            D,
            self.X + dpt,
            oR,
            ot,
            self.refine_focal,
            self.refine_k1,
            self.intrinsics,
        )


class Block:
    """One camera's observations ``sl`` (a slice of the solver's order): the first ``n_free``
    are free points (keys ``free_key`` into Observations.points, unique), the rest rigid ones
    sorted by object (runs starting at ``run_start``, relative to the rigid part, with keys
    ``run_key`` into Observations.objects)."""

    def __init__(
        self,
        cam: int,
        sl: slice,
        n_free: int,
        free_key: np.ndarray,
        run_start: np.ndarray,
        run_key: np.ndarray,
    ):
        self.cam, self.sl, self.n_free = cam, sl, n_free
        self.free_key, self.run_start, self.run_key = free_key, run_start, run_key


class Observations:
    """Active observations ordered for the solver: by camera, then free points (by point), then
    rigid ones (by object), cut into :class:`Block` s. ``idx`` maps back to the problem's order;
    ``points`` / ``objects`` are the free points / objects the active set estimates."""

    def __init__(self, prob, active: np.ndarray):
        idx = np.flatnonzero(active)
        pt = prob.obs_point[idx]
        obj = prob.point_object[pt]
        struct = np.where(obj < 0, pt, prob.points.shape[0] + obj)
        order = np.lexsort((struct, prob.obs_camera[idx]))
        self.idx = idx[order]
        self.cam = prob.obs_camera[self.idx]
        self.pt = pt[order]
        self.obj = obj[order]
        self.uv = prob.obs_uv[self.idx]
        self.w = prob.obs_weight[self.idx]
        self.model = prob.model[self.pt]
        free = self.obj < 0
        self.points, point_key = np.unique(self.pt[free], return_inverse=True)
        self.objects, object_key = np.unique(self.obj[~free], return_inverse=True)
        key = np.empty(self.idx.size, np.int64)
        key[free], key[~free] = point_key.ravel(), object_key.ravel()
        self.blocks: list[Block] = []
        bounds = np.searchsorted(self.cam, np.arange(prob.num_cameras + 1))
        for c in range(prob.num_cameras):
            for a in range(int(bounds[c]), int(bounds[c + 1]), _CHUNK):
                b = min(a + _CHUNK, int(bounds[c + 1]))
                nf = int(np.count_nonzero(free[a:b]))
                rk = key[a + nf : b]
                runs = np.flatnonzero(np.r_[True, rk[1:] != rk[:-1]]) if rk.size else rk
                self.blocks.append(Block(c, slice(a, b), nf, key[a : a + nf], runs, rk[runs]))

    def __len__(self) -> int:
        return int(self.idx.size)


def _cross(a: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(3,k), (2,3,k) -> (2,3,k): a x B[r] for each row r, coordinate-first (np.cross on
    (k,3) rows is slow)."""
    out = np.empty(B.shape)
    out[:, 0] = a[1] * B[:, 2] - a[2] * B[:, 1]
    out[:, 1] = a[2] * B[:, 0] - a[0] * B[:, 2]
    out[:, 2] = a[0] * B[:, 1] - a[1] * B[:, 0]
    return out


def _distort(st: State, c: int, x: np.ndarray, y: np.ndarray):
    """Camera ``c``'s plumb_bob lens on normalised coordinates: (xd, yd, r2, (M00, M01, M11))
    with M = d (xd, yd) / d (x, y) (symmetric)."""
    k1, k2, p1, p2, k3 = st.D[c]
    r2 = x * x + y * y
    if not st.full_lens:  # k1 alone: the rectified images of the people mode
        d = 1.0 + k1 * r2
        return x * d, y * d, r2, (d + 2 * k1 * x * x, 2 * k1 * x * y, d + 2 * k1 * y * y)
    d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d d / d r2
    xy = x * y
    xd = x * d + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    M = (
        d + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x,
        2 * xy * g + 2 * p1 * x + 2 * p2 * y,
        d + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x,
    )
    return xd, yd, r2, M


def _intrinsic_columns(st: State, c: int, x, y, xd, yd, r2, Jc: np.ndarray, col: int) -> None:
    """Fill Jc[:, col:] (2,n,k) with d u / d (each refined intrinsic) of camera ``c``."""
    A = st.K[c, :2, :2] * st.s[c]
    for name in st.intrinsics:
        if name in ("fx", "fy"):
            r = 0 if name == "fx" else 1
            Jc[r, col] = st.s[c] * (xd if r == 0 else yd)
            Jc[1 - r, col] = 0.0
        elif name in ("cx", "cy"):
            Jc[:, col] = 0.0
            Jc[0 if name == "cx" else 1, col] = 1.0
        else:  # d (xd, yd) of the coefficient, through A
            if name in ("k1", "k2", "k3"):
                rn = r2 ** (1 + "k1k2k3".index(name) // 2)
                ex, ey = x * rn, y * rn
            elif name == "p1":
                ex, ey = 2 * x * y, r2 + 2 * y * y
            else:
                ex, ey = r2 + 2 * x * x, 2 * x * y
            Jc[:, col] = A[:, :1] * ex + A[:, 1:] * ey
        col += 1


def project(st: State, ob: Observations, blk: Block, jac: bool):
    """Residuals (k,2) px (projection - observation) of the block's observations; with ``jac``
    also the Jacobians, coordinate-first: w.r.t. the camera block (2,dc,k) and the structure
    block (2,3,k_free) for free points / (2,6,k_rigid) for rigid objects (the block's first
    and second part). Coordinate-first so that every product below runs over contiguous
    length-k rows (the (k,2,n) layout makes numpy loop over tiny 2x3 matrices)."""
    c, sl, nf = blk.cam, blk.sl, blk.n_free
    X = np.empty((sl.stop - sl.start, 3))
    X[:nf] = st.X[ob.pt[sl.start : sl.start + nf]]
    RoM = None
    if nf < X.shape[0]:
        o = ob.obj[sl.start + nf : sl.stop]
        RoM = np.einsum("nij,nj->in", st.oR[o], ob.model[sl.start + nf : sl.stop])
        X[nf:] = RoM.T + st.ot[o]
    Rc = st.R[c]
    RX = Rc @ X.T  # (3,k)
    Xc = RX + st.t[c][:, None]
    z = np.maximum(Xc[2], MIN_DEPTH)
    x, y = Xc[0] / z, Xc[1] / z
    xd, yd, r2, (M00, M01, M11) = _distort(st, c, x, y)
    A = st.K[c, :2, :2] * st.s[c]
    c0 = st.K[c, :2, 2]
    res = np.empty((x.size, 2))
    res[:, 0] = A[0, 0] * xd + A[0, 1] * yd + c0[0] - ob.uv[sl, 0]
    res[:, 1] = A[1, 0] * xd + A[1, 1] * yd + c0[1] - ob.uv[sl, 1]
    if not jac:
        return res
    # d u / d Xc = A M d xn / d Xc, entry by entry
    inv_z = np.where(Xc[2] < MIN_DEPTH, 0.0, 1.0 / z)
    Jc = np.empty((2, st.dc, x.size))
    D = Jc[:, 3:6]
    for r in range(2):
        D[r, 0] = (A[r, 0] * M00 + A[r, 1] * M01) * inv_z
        D[r, 1] = (A[r, 0] * M01 + A[r, 1] * M11) * inv_z
        D[r, 2] = -(D[r, 0] * x + D[r, 1] * y)
    Jc[:, :3] = _cross(RX, D)  # -D [RX]x, row-wise RX x D_r
    col = 6
    if st.refine_focal:
        K2 = st.K[c, :2, :2]
        Jc[:, col] = K2[:, :1] * xd + K2[:, 1:] * yd
        col += 1
    if st.refine_k1:
        Jc[:, col] = A[:, :1] * (x * r2) + A[:, 1:] * (y * r2)
        col += 1
    if st.intrinsics:
        _intrinsic_columns(st, c, x, y, xd, yd, r2, Jc, col)
    dudX = Rc.T @ D  # (2,3,k): row r of d u / d X is D_r Rc
    Jo = np.zeros((2, 6, x.size - nf))
    if RoM is not None:
        Jo[:, :3] = _cross(RoM, dudX[:, :, nf:])
        Jo[:, 3:] = dudX[:, :, nf:]
    return res, Jc, dudX[:, :, :nf], Jo


class Group:
    """One structure group's normal-equation pieces: V (n,ds,ds), gradient gs (n,ds), and the
    transposed camera coupling Wt (n,ds,C,dc), zero for cameras that do not see a structure."""

    def __init__(self, n: int, ds: int, C: int, dc: int):
        self.V = np.zeros((n, ds, ds))
        self.gs = np.zeros((n, ds))
        self.Wt = np.zeros((n, ds, C, dc))

    def add(
        self,
        cam: int,
        keys: np.ndarray,
        runs: np.ndarray | None,
        Jc_w: np.ndarray,
        Js: np.ndarray,
        w: np.ndarray,
        res: np.ndarray,
    ) -> None:
        """Add one camera's observations (Jacobians coordinate-first, as :func:`project`
        gives them) of the structures ``keys`` (unique; with ``runs``, consecutive
        observations of one structure are summed first)."""
        n, ds, C, dc = self.Wt.shape
        Js_w = Js * w
        V = Js_w[0][:, None] * Js[0][None] + Js_w[1][:, None] * Js[1][None]  # (ds,ds,k)
        gs = Js_w[0] * res[:, 0] + Js_w[1] * res[:, 1]  # (ds,k)
        W = Js[0][:, None] * Jc_w[0][None] + Js[1][:, None] * Jc_w[1][None]  # (ds,dc,k)
        if runs is not None:
            V, gs, W = (np.add.reduceat(a, runs, axis=-1) for a in (V, gs, W))
        self.V.reshape(n, ds * ds)[keys] += V.reshape(ds * ds, -1).T
        self.gs[keys] += gs.T
        rows = (keys[:, None] * ds + np.arange(ds)).ravel()
        W = W.transpose(2, 0, 1).reshape(-1, dc)
        if runs is None:  # free points: each (point, camera) once (BundleProblem checks)
            self.Wt.reshape(n * ds, C, dc)[rows, cam] = W
        else:  # an object's observations by one camera may span two blocks
            self.Wt.reshape(n * ds, C, dc)[rows, cam] += W


class NormalEquations:
    """J^T W J and J^T W r of the robustified problem at one state (IRLS weights)."""

    def __init__(self, st: State, ob: Observations, loss: str, scale: float, C: int):
        dc = st.dc
        self.U = np.zeros((C, dc, dc))
        self.gc = np.zeros((C, dc))
        self.free = Group(ob.points.size, 3, C, dc)
        self.rigid = Group(ob.objects.size, 6, C, dc)
        for blk in ob.blocks:
            self._add(st, ob, blk, loss, scale)

    def _add(self, st: State, ob: Observations, blk: Block, loss: str, scale: float) -> None:
        res, Jc, Jp, Jo = project(st, ob, blk, True)
        w = robust_rho(loss, np.einsum("ni,ni->n", res, res), scale)[1] * ob.w[blk.sl]
        Jc_w = Jc * w
        c, nf = blk.cam, blk.n_free
        self.U[c] += Jc_w[0] @ Jc[0].T + Jc_w[1] @ Jc[1].T
        self.gc[c] += Jc_w[0] @ res[:, 0] + Jc_w[1] @ res[:, 1]
        if nf:
            self.free.add(c, blk.free_key, None, Jc_w[:, :, :nf], Jp, w[:nf], res[:nf])
        if nf < res.shape[0]:
            self.rigid.add(c, blk.run_key, blk.run_start, Jc_w[:, :, nf:], Jo, w[nf:], res[nf:])


def damp(A: np.ndarray, mu: float) -> np.ndarray:
    """A + mu diag(A) blockwise (Marquardt), the diagonal clamped away from 0."""
    diag = np.clip(np.diagonal(A, axis1=-2, axis2=-1), 1e-6, 1e32)
    return A + mu * diag[..., :, None] * np.eye(A.shape[-1])


def reduced_system(ne: NormalEquations, mu: float, free_cam: np.ndarray):
    """(S (C dc, C dc), rhs (C dc,), V^-1 per group) of the damped system after eliminating
    the structure; unknowns not in ``free_cam`` (C,dc) get identity rows. None if a structure
    block is singular."""
    C, dc, _ = ne.U.shape
    Ud = damp(ne.U, mu)
    S = np.zeros((C * dc, C * dc))
    for c in range(C):
        S[c * dc : (c + 1) * dc, c * dc : (c + 1) * dc] = Ud[c]
    rhs = -ne.gc.ravel().copy()
    inverses = []
    for g in (ne.free, ne.rigid):
        n, ds = g.V.shape[:2]
        if n == 0:
            inverses.append(g.V)
            continue
        try:
            Vinv = np.linalg.inv(damp(g.V, mu))
        except np.linalg.LinAlgError:
            return None
        inverses.append(Vinv)
        for a in range(0, n, _STRUCT_CHUNK):
            b = min(n, a + _STRUCT_CHUNK)
            Wt = g.Wt[a:b].reshape(b - a, ds, C * dc)
            Z = (Vinv[a:b] @ Wt).reshape(-1, C * dc)  # (W V^-1)^T of each structure, stacked
            S -= Wt.reshape(-1, C * dc).T @ Z
            rhs += Z.T @ g.gs[a:b].ravel()
    fixed = ~free_cam.ravel()
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
        n, ds = g.V.shape[:2]
        if n == 0:
            steps.append(np.zeros((0, ds)))
            continue
        WT_dc = (g.Wt.reshape(n * ds, C * dc) @ dcam.ravel()).reshape(n, ds)
        steps.append(-(Vinv @ (g.gs + WT_dc)[..., None])[..., 0])
    return dcam, steps[0], steps[1]
