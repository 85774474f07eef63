"""Per-camera time offsets refined jointly: one Gauss-Newton over all C offsets at once.

Camera c's frame k shows the scene at time (k + delta_c) / fps. With the rig fixed, the 3D
point of camera c's observation at frame k is the track's point at the reference time k moved
by the track's motion over delta_c frames; equivalently (what is computed) the keypoint is
moved back to the reference time by the displacement of the track's projection between
k + delta_c and k. The displacement comes from the rig's own 3D tracks (all cameras' joint
triangulation) smoothed by a local quadratic in continuous time (timing.kernel_tracks), not
from the noisy 2D samples: interpolating those favours half-frame offsets, whose noise is
lower, and a plain Gaussian mean would flatten fast limb motion and inflate the offsets. The
per-(track, frame, joint) points are eliminated by variable projection: re-triangulated from
all cameras at every evaluation, so the cost is the sum over all cameras of their capped
reprojection errors (each camera's cap TRUNCATE_PX or TRUNCATE_REL x its median error, the
keypoints over it left out) against the joint triangulation, and its Jacobian in the offsets
(forward differences) includes how the points follow them.

Why: Gauss-Seidel (timing.gauss_seidel_offsets) minimises each camera's own cost against the
others' triangulation in turn; that is not a minimum of the joint cost, and it drifts along a
combination of offsets (opposite cameras shifted against each other) the fit barely sees.
The Gauss-Seidel scan stays as the start (it finds the basin up to +-max_frames); the joint
fit then refines all offsets together and gives standard errors that include the cameras'
correlation. The gauge (a common offset of all cameras changes nothing) is fixed by
stepping only in the sum-zero subspace; offsets are reported relative to the median camera.
"""

from __future__ import annotations

import numpy as np

from .timing import (
    SIGNIFICANCE,
    TRUNCATE_PX,
    TRUNCATE_REL,
    _fit_gain_z,
    _fit_gain_z_kernel,
    _project,
    _two_camera_offset,
    gauss_seidel_offsets,
    kernel_tracks,
)
from .tracks import shift_in_time, triangulate

#: the estimators PeopleOptions.time_method may name ("gauss_seidel_partial": Gauss-Seidel
#: with the 3D tracks also evaluated where part of the kernel's samples are missing, the
#: default before; timing.kernel_tracks says why that biases the offsets)
TIME_METHODS = ("joint", "gauss_seidel", "gauss_seidel_partial")
#: the joint significance tests PeopleOptions.time_test may name: "kernel" (the default,
#: timing._fit_gain_z_kernel: the other cameras' 2D tracks smoothed by the estimator's
#: Gaussian and evaluated at each camera's capture times) or "interpolated" (the former,
#: timing._fit_gain_z: moved by linear interpolation; it zeroed humanm3_4 s2's true offsets)
TIME_TESTS = ("kernel", "interpolated")
#: Gauss-Seidel rounds of the start (the first scans +-max_frames; the second settles the
#: cameras scanned first against the others' new offsets)
START_ROUNDS = 2
#: frames: the finite difference of the Jacobian (the residuals are nearly linear in delta)
STEP = 0.1
#: frames: sd of the Gaussian weights of the local quadratic fit the displacements come from
JOINT_SIGMA = 1.0
#: outer iterations (velocities, caps and inliers re-evaluated at each) and their stop (frames)
ITERATIONS = 8
TOL = 0.002


class _Problem:
    """The joint cost at fixed 3D tracks X (T,F,J,3) and inliers: each keypoint of camera c
    (U (C,T,F,J,2) px) moved to the reference time k by the displacement of X's projection
    between k + delta_c and k (X smoothed by timing.kernel_tracks, Gaussian in continuous
    time: no sub-frame position has less noise), all cameras triangulated together."""

    def __init__(self, P: np.ndarray, U: np.ndarray, X: np.ndarray, inlier: np.ndarray):
        self.P, self.X = P, X
        self.U = np.where(inlier[..., None], U, np.nan)
        self.where = [np.nonzero(np.all(np.isfinite(u), axis=-1)) for u in self.U]
        self.at_k = [
            _project(P[c], kernel_tracks(X, w, np.zeros(1), JOINT_SIGMA, True, False)[0])
            for c, w in enumerate(self.where)
        ]

    def moved(self, c: int, deltas: np.ndarray) -> np.ndarray:
        """(D,T,F,J,2) px: camera c's keypoints moved to the reference times, for D deltas."""
        w = self.where[c]
        out = np.full((len(deltas),) + self.U.shape[1:], np.nan)
        at = kernel_tracks(self.X, w, deltas, JOINT_SIGMA, True, False)
        shift = _project(self.P[c], at) - self.at_k[c]
        out[(slice(None),) + w] = self.U[c][w] - shift
        return out

    def residuals(self, moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(C,T,F,J,2) px reprojection minus moved keypoints (NaN: unseen, outlier, no point)
        and the joint triangulation (T,F,J,3) of the moved keypoints (C,T,F,J,2)."""
        X = triangulate(self.P, moved)
        return np.stack([_project(self.P[c], X) for c in range(len(self.P))]) - moved, X

    def at(self, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """residuals and triangulation at offsets delta (C,) frames."""
        return self.residuals(np.stack([self.moved(c, delta[c : c + 1])[0] for c in range(len(delta))]))

    def jacobian(self, delta: np.ndarray, r0: np.ndarray) -> np.ndarray:
        """(C,C,T,F,J,2) px/frame: d residuals / d delta_d for every camera d (forward
        differences of STEP frames, the points re-triangulated: variable projection)."""
        pairs = [self.moved(c, np.array([delta[c], delta[c] + STEP])) for c in range(len(delta))]
        base = np.stack([m[0] for m in pairs])
        cols = []
        for d in range(len(delta)):
            moved = base.copy()
            moved[d] = pairs[d][1]
            cols.append((self.residuals(moved)[0] - r0) / STEP)
        return np.stack(cols)


def _caps(r: np.ndarray) -> np.ndarray:
    """(C,) px: each camera's cap, TRUNCATE_PX or TRUNCATE_REL x its median error."""
    e = np.linalg.norm(r, axis=-1).reshape(len(r), -1)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(np.isfinite(e), e, np.nan), axis=1)
    return np.maximum(TRUNCATE_PX, TRUNCATE_REL * np.nan_to_num(med, nan=0.0))


def _capped_cost(r: np.ndarray, cap: np.ndarray) -> float:
    """Sum of the squared errors capped at cap_c^2 (px^2) over the defined residuals."""
    e2 = np.sum(r**2, axis=-1)
    e2 = np.minimum(e2, (cap**2)[:, None, None, None])
    return float(np.sum(e2[np.isfinite(e2)]))


def _linearise(
    P: np.ndarray, U: np.ndarray, X: np.ndarray, delta: np.ndarray
) -> tuple[_Problem, np.ndarray, np.ndarray]:
    """The problem at 3D tracks X (T,F,J,3) and offsets ``delta`` (C,) frames: each camera's
    cap from its errors there, inliers = keypoints under the cap; and the caps (C,) px and
    the inliers' residuals (C,T,F,J,2) px at delta."""
    C = P.shape[0]
    r = _Problem(P, U, X, np.ones(U.shape[:-1], bool)).at(delta)[0]
    cap = _caps(r)
    inlier = np.sum(r**2, axis=-1) < (cap**2).reshape((C,) + (1,) * (r.ndim - 2))
    prob = _Problem(P, U, X, inlier)
    return prob, cap, prob.at(delta)[0]


def _normal(
    J: np.ndarray, r: np.ndarray, B: np.ndarray, track: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton in the sum-zero coordinates z (delta = B z): H (C-1,C-1), gradient g
    (C-1,) and the per-track gradients' outer sum S (C-1,C-1) (sandwich: a track's errors
    are correlated), over the residuals defined in r and in every column of J."""
    C = J.shape[0]
    Jf = J.reshape(C, -1)
    rf = r.reshape(-1)
    tr = np.broadcast_to(track, r.shape).reshape(-1)
    ok = np.isfinite(rf) & np.all(np.isfinite(Jf), axis=0)
    Jz = B.T @ Jf[:, ok]  # (C-1,N)
    H = Jz @ Jz.T
    g = Jz @ rf[ok]
    _, t = np.unique(tr[ok], return_inverse=True)
    per = np.stack(
        [np.bincount(t, Jz[i] * rf[ok], minlength=t.max() + 1 if t.size else 0) for i in range(len(Jz))]
    )  # (C-1,tracks)
    n = per.shape[1]
    S = per @ per.T * n / max(n - 1, 1)
    return H, g, S


def refine_joint(P: np.ndarray, U: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C,) offsets in frames of the cameras P (C,3,4) with 2D tracks U (C,T,F,J,2) px,
    refined jointly from ``start`` (C,) frames, relative to the median camera; and their (C,)
    standard errors (frames, sandwich over tracks, in that median gauge)."""
    C = P.shape[0]
    B = np.linalg.svd(np.eye(C) - 1.0 / C)[0][:, : C - 1]  # orthonormal sum-zero basis
    track = np.arange(U.shape[1])[None, :, None, None, None]
    delta = np.asarray(start, float) - np.mean(start)
    X = triangulate(P, np.stack([shift_in_time(U[c], delta[c]) for c in range(C)]))
    cov = np.full((C - 1, C - 1), np.nan)
    for _ in range(ITERATIONS):
        prob, cap, r = _linearise(P, U, X, delta)
        H, g, S = _normal(prob.jacobian(delta, r), r, B, track)
        try:
            Hi = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            break
        cov = Hi @ S @ Hi
        step = B @ (-Hi @ g)
        cost = _capped_cost(r, cap)
        for _halving in range(6):  # a step that raises the capped cost is shortened
            r_new, X_new = prob.at(delta + step)
            if _capped_cost(r_new, cap) <= cost:
                break
            step = step / 2
        else:
            break
        delta, X = delta + step, X_new
        if np.max(np.abs(step)) < TOL:
            break
    med = np.median(delta)
    return delta - med, _median_gauge_sd(delta, B @ cov @ B.T)


def _median_gauge_sd(delta: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(C,) frames: the standard errors of delta_c - median(delta) given the covariance cov
    (C,C) of delta (the median a fixed selection of one or the mean of two cameras)."""
    C = len(delta)
    order = np.argsort(delta)
    m = np.zeros(C)
    m[order[(C - 1) // 2]] += 0.5
    m[order[C // 2]] += 0.5
    A = np.eye(C) - m[None]
    var = np.einsum("ci,ij,cj->c", A, cov, A)
    return np.sqrt(np.where(var > 0, var, np.nan))


def estimate_offsets(
    P: np.ndarray,
    U: np.ndarray,
    max_frames: float,
    method: str = "joint",
    start: np.ndarray | None = None,
    test: str = "kernel",
) -> tuple[np.ndarray, np.ndarray]:
    """(C,) offsets in frames of the cameras with projection matrices P (C,3,4) and 2D tracks
    U (C,T,F,J,2) px, relative to the median camera, and their (C,) standard errors (frames;
    NaN for a two-camera rig). ``method``: "joint" (the Gauss-Seidel scan, START_ROUNDS
    rounds, then refine_joint), "gauss_seidel" (timing.gauss_seidel_offsets to convergence)
    or "gauss_seidel_partial" (the same on partial kernel windows, timing.kernel_tracks).
    ``start`` (C,) frames: offsets already close (a previous rig): no scan. Then the
    significance tests: an offset within SIGNIFICANCE standard errors of 0 is set to
    0, and all are when together they do not improve the cross-view fit by SIGNIFICANCE
    standard errors, so a synchronised rig stays synchronised (``test``: "kernel",
    timing._fit_gain_z_kernel, or "interpolated", timing._fit_gain_z, the former)."""
    if method not in TIME_METHODS:
        raise ValueError(f"time offsets: method {method!r} is not one of {TIME_METHODS}")
    if test not in TIME_TESTS:
        raise ValueError(f"time offsets: test {test!r} is not one of {TIME_TESTS}")
    C = P.shape[0]
    if C == 2:
        return _two_camera_offset(P, U, max_frames), np.full(2, np.nan)
    complete = method != "gauss_seidel_partial"
    if method != "joint":
        delta, sd = gauss_seidel_offsets(P, U, max_frames, start=start, complete=complete)
    else:
        if start is None:
            start = gauss_seidel_offsets(P, U, max_frames, rounds=START_ROUNDS)[0]
        delta, sd = refine_joint(P, U, start)
    sd = np.where(np.isfinite(sd), sd, np.inf)
    delta[np.abs(delta) < SIGNIFICANCE * sd] = 0.0
    if np.any(delta):
        z = _fit_gain_z_kernel(P, U, delta) if test == "kernel" else _fit_gain_z(P, U, delta, complete)
        if z < SIGNIFICANCE:
            delta[:] = 0.0
    return delta, sd
