"""Per-joint uncertainty of a triangulated point, and the pose confidence built on it.

A joint X (world m) triangulated from the views m that support it (reprojection error under
``tau_kps`` at X) has the first-order covariance of the least-squares estimate

    cov(X) = s^2 (sum_m J_m^T J_m)^-1,   J_m = d pi(P_m X) / dX   (2x3, px/m)

where s^2 is the keypoint noise variance (px^2), estimated from the residuals r (px) of the
supporting views in two levels, since two views leave one residual degree of freedom only:
the pose's noise, pooled over its joints j (n_j views each) with a prior of ``prior_px`` worth
``prior_dof`` degrees of freedom, is the prior of each joint's, worth ``prior_dof`` again:

    s_pose^2 = (prior_dof * prior_px^2 + sum_j sum_m |r_jm|^2) / (prior_dof + sum_j (2 n_j - 3))
    s_j^2    = (prior_dof * s_pose^2 + sum_m |r_jm|^2) / (prior_dof + 2 n_j - 3).

The pooled level adapts the scale to the frontend's noise (a fixed 2 px prior dominated the
few-view joints: on the simulated study scenes the 3D errors were 1.2x (medium noise) to 1.7x
(hard) the predicted ones; pooled, 0.92-1.01x on every scene: doc/tracking.md), the joint level
keeps the joints' own noise (a wrist is noisier than a hip).

So a joint seen by few views at a narrow angle (a weak geometry) and a joint whose views disagree
(a wrong member, a bad keypoint) both get a large uncertainty. The published per-joint standard
deviation is sqrt(trace(cov) / 3): the RMS over the three world axes, metres.

The pose confidence ranks poses by their predicted error: ``1 / (1 + e / ref_m)`` with e the
RMS over the pose's finite joints of sqrt(trace(cov)) (the predicted 3D error, m); 1 for a
perfect pose, 0.5 at ``ref_m``. The triangulation's ``pose_score: uncertainty`` (default)
multiplies it with the paper's score (the members' mean detection score), so a well-triangulated
false positive (a low-score bystander) still ranks low and a confident detection with a weak
geometry or disagreeing views ranks below a well-supported one (doc/design.md gives the AP
figures that chose it).
"""

from __future__ import annotations

import numpy as np

#: below this |det| the normal matrix of a joint is singular (one view, or rays at ~0 angle)
_SINGULAR_DET = 1e-30


def joint_covariance(
    P: np.ndarray,
    X: np.ndarray,
    uv: np.ndarray,
    usable: np.ndarray,
    tau_px: float,
    prior_px: float,
    prior_dof: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (C,J,3,3) m^2 of every triangulated joint and its supporting views (C,J).

    P (C,M,3,4) world -> rectified px of each member view; X (C,J,3) world m (NaN = missing);
    uv (C,M,J,2) px; usable (C,M,J) views that observed the joint. A view supports a joint when
    its reprojection error at X is under ``tau_px``. Joints with fewer than two supporting views
    or a singular geometry get NaN.
    """
    C, M, J = usable.shape
    Xh = np.concatenate([X, np.ones((C, J, 1))], axis=-1)  # (C,J,4)
    # matmul: faster than einsum or broadcast sums for these small batched contractions
    x = np.matmul(P[:, :, None], Xh[:, None, :, :, None])[..., 0]  # (C,M,J,3) homogeneous
    z = x[..., 2]
    with np.errstate(all="ignore"):
        proj = x[..., :2] / z[..., None]
        r2 = ((proj - uv) ** 2).sum(-1)  # (C,M,J) px^2
        support = usable & (z > 0) & (r2 < tau_px * tau_px)
        # d(u, v)/dX = (P[:2, :3] - (u, v)^T P[2, :3]) / z
        jac = (P[:, :, None, :2, :3] - proj[..., :, None] * P[:, :, None, 2:3, :3]) / z[..., None, None]
        jac = np.where(support[..., None, None], jac, 0.0)
        rows = jac.transpose(0, 2, 1, 3, 4).reshape(C, J, 2 * M, 3)  # (C,J,2M,3)
        H = rows.swapaxes(-1, -2) @ rows  # (C,J,3,3) px^2/m^2: sum over views of J_m^T J_m
        n = support.sum(1)  # (C,J)
        dof = np.where(n >= 2, 2 * n - 3, 0)
        rss = np.where(support, r2, 0.0).sum(1)  # (C,J) px^2
        # the pose's keypoint noise, pooled over its joints (tens of residual degrees of
        # freedom), is each joint's prior: a joint seen by two views has one of its own
        pose_s2 = (prior_dof * prior_px**2 + rss.sum(1)) / (prior_dof + dof.sum(1))  # (C,)
        s2 = (prior_dof * pose_s2[:, None] + rss) / (prior_dof + dof)
    adj, det = _adjugate_det(H)
    ok = (n >= 2) & np.isfinite(X).all(-1) & (np.abs(det) > _SINGULAR_DET)
    cov = np.full((C, J, 3, 3), np.nan)
    if ok.any():
        cov[ok] = adj[ok] * (s2[ok] / det[ok])[:, None, None]
    return cov, n


def _adjugate_det(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adjugate (…,3,3) and determinant (…) of symmetric 3x3 matrices in closed form:
    inv(H) = adj / det. Closed form, not np.linalg: LAPACK's per-matrix call dominates for the
    hundreds of 3x3 matrices of a frame."""
    a, b, c = H[..., 0, 0], H[..., 0, 1], H[..., 0, 2]
    d, e, f = H[..., 1, 1], H[..., 1, 2], H[..., 2, 2]
    adj = np.empty(H.shape)
    adj[..., 0, 0] = d * f - e * e
    adj[..., 0, 1] = adj[..., 1, 0] = c * e - b * f
    adj[..., 0, 2] = adj[..., 2, 0] = b * e - c * d
    adj[..., 1, 1] = a * f - c * c
    adj[..., 1, 2] = adj[..., 2, 1] = b * c - a * e
    adj[..., 2, 2] = a * d - b * b
    det = a * adj[..., 0, 0] + b * adj[..., 0, 1] + c * adj[..., 0, 2]
    return adj, det


def joint_std(cov: np.ndarray) -> np.ndarray:
    """(…,J) per-joint standard deviation, m: sqrt(trace(cov)/3), the RMS over world axes."""
    return np.sqrt(np.trace(cov, axis1=-2, axis2=-1) / 3.0)


def pose_confidence(std: np.ndarray, ref_m: float) -> np.ndarray:
    """(P,) confidence in (0, 1] from per-joint std (P,J) m: 1 / (1 + e / ref_m), e = RMS over
    finite joints of the predicted 3D error sqrt(3) * std; 0 for a pose with no finite joint."""
    with np.errstate(all="ignore"):
        finite = np.isfinite(std)
        mean_var = np.where(finite, 3.0 * std**2, 0.0).sum(-1) / finite.sum(-1)
        e = np.sqrt(mean_var)
        conf = 1.0 / (1.0 + e / ref_m)
    return np.where(finite.any(-1), conf, 0.0)


def pose_scores(detection_scores: np.ndarray, std: np.ndarray, mode: str, ref_m: float) -> np.ndarray:
    """(P,) published score: ``paper`` = the members' mean detection score; ``uncertainty`` =
    that times :func:`pose_confidence` of the per-joint std (P,J) m."""
    if mode == "paper":
        return np.asarray(detection_scores, dtype=np.float64)
    return detection_scores * pose_confidence(std, ref_m)
