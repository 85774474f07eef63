"""Batched similarity Procrustes (Umeyama): rotation, translation and uniform scale.

Shared by the association cost (PA-MPJPE between two detections' 3D keypoints: the fast
``pa_mpjpe_finite`` / ``pa_mpjpe_columns`` for validated input, in closed form per pair via
Horn's quaternion, with the stacked SVD as fallback for near-degenerate poses) and the
evaluation metrics (``pa_mpjpe``, masked, SVD). Units are whatever the inputs use (metres here).
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.procrustes_terms import (
    ADJ_ENTRY,
    ADJ_MINOR,
    ADJ_SIGN,
    fill_key_matrix,
    fill_rotation,
)

#: fewer valid joints than this leave the similarity under-determined -> NaN
MIN_JOINTS = 3


def _valid_mask(X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    if X.shape != Y.shape or X.ndim < 2 or X.shape[-1] != 3:
        raise ValueError(f"procrustes: X and Y must both be (...,J,3), got {X.shape} and {Y.shape}")
    valid = np.isfinite(X).all(-1) & np.isfinite(Y).all(-1)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        try:
            valid = valid & np.broadcast_to(mask, valid.shape)
        except ValueError:
            raise ValueError(
                f"procrustes: mask shape {mask.shape} does not match joints {valid.shape}"
            ) from None
    return valid


def procrustes_align(
    X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Align X onto Y with the least-squares similarity s R X + t (batched over leading dims).

    X, Y: (...,J,3); mask: (...,J) bool or None. Joints that are masked out or non-finite in
    either input are ignored when fitting. Returns (aligned X (...,J,3), s (...), R (...,3,3),
    t (...,3)); all NaN where fewer than 3 joints are usable.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    valid = _valid_mask(X, Y, mask)
    w = valid.astype(np.float64)[..., None]
    n = w.sum(-2)  # (...,1)
    ok = n[..., 0] >= MIN_JOINTS
    n_safe = np.maximum(n, 1.0)
    Xz = np.where(valid[..., None], X, 0.0)
    Yz = np.where(valid[..., None], Y, 0.0)
    mu_x = Xz.sum(-2) / n_safe
    mu_y = Yz.sum(-2) / n_safe
    Xc = (Xz - mu_x[..., None, :]) * w
    Yc = (Yz - mu_y[..., None, :]) * w
    var_x = (Xc**2).sum((-2, -1)) / n_safe[..., 0]
    cov = np.swapaxes(Yc, -1, -2) @ Xc / n_safe[..., None]
    U, S, Vt = np.linalg.svd(cov)
    # reflection guard: flip the weakest axis when the best orthogonal map is improper
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    R = U @ Vt
    trace = S[..., 0] + S[..., 1] + d * S[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(var_x > 0, trace / var_x, 0.0)
    t = mu_y - s[..., None] * np.einsum("...ij,...j->...i", R, mu_x)
    aligned = s[..., None, None] * (X @ np.swapaxes(R, -1, -2)) + t[..., None, :]
    nan = ~ok
    aligned[nan] = np.nan
    s = np.where(nan, np.nan, s)
    R[nan] = np.nan
    t[nan] = np.nan
    return aligned, s, R, t


def pa_mpjpe(X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(...) mean joint distance after similarity-aligning X onto Y (units of Y).

    Joints masked out or non-finite in either input are ignored; NaN where fewer than 3
    joints are usable.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    aligned = procrustes_align(X, Y, mask)[0]
    valid = _valid_mask(X, Y, mask)
    dist = np.linalg.norm(aligned - Y, axis=-1)
    n = valid.sum(-1)
    with np.errstate(invalid="ignore"):
        out = np.where(valid, dist, 0.0).sum(-1) / np.maximum(n, 1)
    return np.where(n >= MIN_JOINTS, out, np.nan)


def pa_mpjpe_finite(X: np.ndarray, Y: np.ndarray, backend: str = "auto") -> np.ndarray:
    """(S,) PA-MPJPE (units of Y) of X (S,J,3) similarity-aligned onto Y (S,J,3), finite input.

    The same Umeyama alignment as pa_mpjpe (rotation with reflection guard,
    translation, uniform scale) without its mask/NaN handling, which validated detections do
    not need. Fewer than 3 joints do not fix a similarity (any two point pairs align exactly),
    so the cost is NaN (= gated) then. See :func:`pa_mpjpe_columns` (the same on
    coordinate-first arrays, which it computes on) and :func:`pa_mpjpe_pairs` (backend).
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    S = X.shape[0]
    columns = np.concatenate([X, Y]).transpose(2, 1, 0)  # (3,J,2S): X's rows, then Y's
    return pa_mpjpe_pairs(columns, np.arange(S), S + np.arange(S), backend)


#: relative eigenvalue gap (product of the three gaps over ||H||_F^3) under which the closed
#: form hands a pair to the SVD: its rotation is then ill-determined (near-degenerate poses)
#: and the quaternion's rounding error would grow as 1/gap (realistic body poses: >= 0.9)
_QCP_MIN_GAP = 1e-6
#: Newton steps on the characteristic quartic (from an upper bound, monotone: 4-6 are used on
#: detections of one person, ~15 on unrelated random poses)
_QCP_MAX_STEPS = 60


def pa_mpjpe_columns(Xt: np.ndarray, Yt: np.ndarray) -> np.ndarray:
    """(S,) PA-MPJPE of Xt onto Yt given coordinate-first (3,J,S) float64, finite (any strides).

    Closed form per pair, vectorised over S (a stacked LAPACK SVD per 3x3 matrix dominated
    the association's cost stage): the optimal rotation is the unit
    quaternion of the largest eigenvalue of Horn's 4x4 key matrix of the cross-covariance
    (quaternion characteristic polynomial, Theobald 2005 / Liu et al. 2010): the eigenvalue by
    Newton from an upper bound, the eigenvector from the adjugate of (K - lambda I). The
    eigenvalue equals the SVD's trace term s1 + s2 + d s3 (d: reflection guard), so the scale,
    rotation and cost equal the SVD path's to rounding; pairs with a near-degenerate
    eigenvalue gap take the SVD path itself (_umeyama_svd).
    """
    S = Xt.shape[-1]
    if Xt.shape[1] < MIN_JOINTS:
        return np.full(S, np.nan)
    if S == 1:  # numpy sums a lone pair's joints in another order: keep results batch-free
        return pa_mpjpe_columns(np.repeat(Xt, 2, axis=2), np.repeat(Yt, 2, axis=2))[:1]
    # centred copies, contiguous per coordinate: every later step runs on (J,S) / (S,) rows
    Xc, Yc = _centred(Xt), _centred(Yt)
    H = np.einsum("ajs,bjs->abs", Xc, Yc)  # sum_j x_a y_b (Horn's S_ab, x aligned onto y)
    gx = np.einsum("ajs,ajs->s", Xc, Xc)
    lam, ok = _qcp_eigenvalue(H, gx, np.einsum("ajs,ajs->s", Yc, Yc))
    R = _qcp_rotation(H, lam)  # (3,3,S), R x ~ y
    with np.errstate(divide="ignore", invalid="ignore"):
        R *= np.where(gx > 0, lam / gx, 0.0)  # times the scale
    sq = np.zeros_like(Xc[0])
    for a in range(3):
        r = R[a, 0] * Xc[0]
        r += R[a, 1] * Xc[1]
        r += R[a, 2] * Xc[2]
        r -= Yc[a]
        r *= r
        sq += r
    out = np.sqrt(sq, out=sq).mean(axis=0)
    bad = np.flatnonzero(~ok)
    if bad.size:
        out[bad] = _umeyama_svd(Xc[..., bad].transpose(2, 1, 0), Yc[..., bad].transpose(2, 1, 0))
    return out


def pa_mpjpe_pairs(columns: np.ndarray, a: np.ndarray, b: np.ndarray, backend: str = "auto") -> np.ndarray:
    """(S,) PA-MPJPE of detection a[s] aligned onto b[s]: :func:`pa_mpjpe_columns` of
    ``columns[:, :, a]`` onto ``columns[:, :, b]`` for columns (3,J,N) float64 finite.

    backend: ``numba`` (core/geometry/procrustes_kernel.py: the same steps per pair, reading the
    columns in place; ~1e-16 relative from numpy's summation order), ``numpy``, or ``auto``
    (numba when installed). Near-degenerate pairs take the SVD path in both."""
    from maem_ros.core.geometry import procrustes_kernel

    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    if backend not in ("auto", "numba", "numpy"):
        raise ValueError(f"backend: expected auto, numba or numpy, got {backend!r}")
    if backend == "numba" and not procrustes_kernel.have_numba():
        raise ValueError("backend: 'numba' requested but numba is not installed")
    if (
        backend == "numpy"
        or not procrustes_kernel.have_numba()
        or columns.shape[1] < MIN_JOINTS
        or a.size == 0
    ):
        return pa_mpjpe_columns(columns[:, :, a], columns[:, :, b])
    out, ok = procrustes_kernel.pair_costs(columns, a, b, _QCP_MAX_STEPS, _QCP_MIN_GAP)
    bad = np.flatnonzero(~ok)
    if bad.size:
        Xc, Yc = (_centred(columns[:, :, v[bad]]) for v in (a, b))
        out[bad] = _umeyama_svd(Xc.transpose(2, 1, 0), Yc.transpose(2, 1, 0))
    return out


def _centred(Xt: np.ndarray) -> np.ndarray:
    """(3,J,S) coordinate-first points minus their mean over the joints, a C-contiguous copy."""
    Xc = np.array(Xt, dtype=np.float64, order="C")
    Xc -= Xc.mean(axis=1, keepdims=True)
    return Xc


def _qcp_eigenvalue(H: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(largest eigenvalue of Horn's key matrix (S,), well separated (S,) bool) of H (3,3,S).

    The characteristic polynomial of the traceless key matrix K is
    l^4 - 2 ||H||_F^2 l^2 - 8 det(H) l + det(K); Newton from min(sqrt(gx gy), sqrt(3) ||H||_F)
    (both bound the nuclear norm of H, hence the largest root) converges monotonically.
    """
    f2 = np.einsum("abs,abs->s", H, H)
    c2 = -2.0 * f2
    c1 = -8.0 * _det3(H)
    c0 = _det4(_key_matrix(H))
    frob = np.sqrt(f2)
    lam = np.minimum(np.sqrt(gx * gy), np.sqrt(3.0) * frob)
    tol = 1e-13 * frob
    active = np.ones(lam.shape, bool)  # a converged pair stops: its result is its own
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(_QCP_MAX_STEPS):
            l2 = lam * lam
            p = (l2 + c2) * l2 + c1 * lam + c0
            dp = (4.0 * l2 + 2.0 * c2) * lam + c1
            step = np.where(active & (dp > 0), p / dp, 0.0)
            lam -= step
            active &= np.abs(step) > tol
            if not active.any():
                break
    l2 = lam * lam
    dp = (4.0 * l2 + 2.0 * c2) * lam + c1  # = product of the gaps to the other eigenvalues
    return lam, ~active & (dp > _QCP_MIN_GAP * f2 * frob)


#: column pairs of the 2x2 minors
_MINOR_I, _MINOR_J = np.array([0, 0, 0, 1, 1, 2]), np.array([1, 2, 3, 2, 3, 3])


def _key_matrix(H: np.ndarray) -> np.ndarray:
    """(4,4,S) Horn's symmetric key matrix of H (3,3,S) (H[a, b] = sum x_a y_b).

    Entry by entry (not a matrix product), like every step of the closed form: each pair's
    result depends on its own numbers only, not on the batch it is computed in."""
    K = np.empty((4, 4) + H.shape[2:])
    fill_key_matrix(K, H[0, 0], H[0, 1], H[0, 2], H[1, 0], H[1, 1], H[1, 2], H[2, 0], H[2, 1], H[2, 2])
    return K


def _det3(a: np.ndarray) -> np.ndarray:
    """Determinants of (3,3,S) matrices."""
    return (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )


def _minors(a: np.ndarray) -> np.ndarray:
    """(12,S) 2x2 minors of rows (0,1), then of rows (2,3), of (4,4,S) matrices, columns
    (01, 02, 03, 12, 13, 23)."""
    top, low = a[0::2], a[1::2]  # rows (0,2) and (1,3): both minor families at once
    m = top[:, _MINOR_I] * low[:, _MINOR_J] - low[:, _MINOR_I] * top[:, _MINOR_J]  # (2,6,S)
    return m.reshape(12, -1)


def _det4(a: np.ndarray) -> np.ndarray:
    """Determinants of (4,4,S) matrices (Laplace expansion over the top two rows)."""
    m = _minors(a)
    s, c = m[:6], m[6:]
    return s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]


def _adjugate4(a: np.ndarray) -> np.ndarray:
    """(4,4,S) adjugates of (4,4,S) matrices, from the 2x2 minors."""
    m = _minors(a)
    flat = a.reshape(16, -1)
    terms = flat[ADJ_ENTRY] * m[ADJ_MINOR]  # (16,3,S)
    terms *= ADJ_SIGN[..., None]
    return terms.sum(axis=1).reshape(a.shape)


def _qcp_rotation(H: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """(3,3,S) rotations of the unit quaternions (eigenvectors of the key matrix of H for
    eigenvalue lam): the adjugate of K - lam I has rank one, q q^T up to scale; its column
    with the largest diagonal entry is the best-conditioned multiple of q."""
    A = _key_matrix(H)
    A[np.arange(4), np.arange(4)] -= lam
    adj = _adjugate4(A)
    best = np.argmax(np.abs(adj[np.arange(4), np.arange(4)]), axis=0)
    q = np.take_along_axis(adj, best[None, None, :], axis=1)[:, 0]  # (4,S)
    with np.errstate(divide="ignore", invalid="ignore"):
        q /= np.sqrt(np.einsum("ks,ks->s", q, q))
    R = np.empty((3, 3) + lam.shape)
    fill_rotation(R, q[0], q[1], q[2], q[3])
    return R


def _umeyama_svd(Xc: np.ndarray, Yc: np.ndarray) -> np.ndarray:
    """(S,) PA-MPJPE of centred Xc (S,J,3) onto centred Yc (S,J,3) by one stacked SVD of the
    3x3 covariances (the closed form's reference and its fallback)."""
    U, S, Vt = np.linalg.svd(np.matmul(Yc.transpose(0, 2, 1), Xc))
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    R = np.matmul(U, Vt)
    var = np.einsum("sjk,sjk->s", Xc, Xc)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(var > 0, (S[:, 0] + S[:, 1] + d * S[:, 2]) / var, 0.0)
    aligned = scale[:, None, None] * np.matmul(Xc, R.transpose(0, 2, 1))
    return np.linalg.norm(aligned - Yc, axis=2).mean(axis=1)
