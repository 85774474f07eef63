"""Per-camera capture time offsets from the people's motion.

Camera c's frame k shows the scene at time (k + delta_c) / fps. For each camera, its 2D tracks
are compared with the 3D tracks triangulated from the other cameras (each moved to the
reference times by its own current offset), smoothed and evaluated at k + delta by a narrow
Gaussian kernel in continuous time (kernel_tracks, only where none of the samples it weighs
is missing): the delta with the smallest robust reprojection error wins (a scan, then a
parabola through the best three values, then a fine scan), for every camera in turn, until
the offsets settle. Offsets are relative; the median
camera's is taken as 0, so that cameras in sync with most of the rig come out at 0.

The errors are capped (TRUNCATE_PX, raised with the keypoints' own noise). Each offset comes
with a standard error (offset_sd: Gauss-Newton curvature, sandwich over tracks); two tests
keep a synchronised rig at 0: an offset within SIGNIFICANCE standard errors of 0 is dropped,
and all of them are when together they do not improve the cross-view fit over a synchronised
rig by SIGNIFICANCE standard errors of that gain (_fit_gain_z_kernel, in the same kernel
model; _fit_gain_z the former, with linear interpolation). The second catches what the
first cannot: on humanm3_4 (4 person-height cameras, 10-20 people, synchronised) Gauss-Seidel
on partial windows settled at +-5-10 ms, each offset 10-20 of its own standard errors from 0,
while the fit with them was worse than with none; on complete windows up to 3.3 ms (z < 0).
"""

from __future__ import annotations

import numpy as np

from .tracks import shift_in_time, triangulate

#: px: a joint's reprojection error counts at most this much (an outlier costs the same anywhere)
#: on clean keypoints; noisier ones raise the cap to TRUNCATE_REL x their median error
TRUNCATE_PX = 6.0
#: the cap relative to the median error at the current offset: real detectors (MediaPipe at
#: 4-6 px, against 3D triangulated from 2-3 other noisy views: 11-17 px median) would
#: otherwise leave most observations capped, and the cost a count of the few under the cap
TRUNCATE_REL = 1.8
#: an offset is kept only when it is this many standard errors from the rig's common time
SIGNIFICANCE = 3.0
#: frames: sd of the Gaussian the 3D tracks are smoothed with in continuous time (kernel_tracks)
SMOOTH_SIGMA = 0.7
#: the kernel is cut at this many sd (the weight there is 1e-3 of the centre's)
KERNEL_REACH = 3.0
#: frames: a scan reaching further than this finds the basin on partial windows (a complete
#: window over the whole +-max_offset scan would leave short tracks without any entry)
COMPLETE_SCAN_REACH = 1.0


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = X @ P[:, :3].T + P[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h[..., 2:] > 0, h[..., :2] / h[..., 2:], np.nan)


def kernel_tracks(
    X: np.ndarray,
    where: tuple[np.ndarray, ...],
    deltas: np.ndarray,
    sigma: float = SMOOTH_SIGMA,
    quadratic: bool = False,
    complete: bool = True,
) -> np.ndarray:
    """(D,N,dim) tracks X (T,F,J,dim: 3D points m, or 2D keypoints px) smoothed by a
    Gaussian kernel of ``sigma`` frames and evaluated at the continuous frame positions
    k + delta of the N entries ``where`` (3 arrays: track, frame k, joint), for each of the
    D ``deltas``. ``complete``: NaN unless
    every sample the kernel weighs (KERNEL_REACH sd around k + delta) is present; otherwise
    (the method before, time_method "gauss_seidel_partial") NaN only where the track lacks
    either frame around k + delta, the missing samples left out of the mean.

    Why a kernel in continuous time: linear interpolation of noisy samples has half the noise
    variance half-way between two frames than at a frame, and smoothing at the frames first
    (then interpolating) keeps part of that modulation, which pulls every offset towards half
    a frame; a Gaussian wider than about half a frame has the same noise at any sub-frame
    position. A narrow one: wider kernels flatten fast limb motion, and that bias (with
    occluded, broken tracks) is larger than the noise they remove. The kernel is linear in X:
    the samples around every entry are gathered once and all deltas weigh them in one product
    (only the observed entries are evaluated).

    Why complete windows: a mean over fewer samples is noisier, so where a sample is missing
    (a track's end, a joint occluded or unmatched in a frame) the expected squared error
    grows with the weight the missing sample would get, i.e. with delta on the gap's side,
    and every such entry pulls the offset away from its gaps. On the bench's fragmented
    tracks (humanm3_4 s0: 169 tracks of 22 people) that bias alone moves offsets by ~0.2
    frame (noise-free keypoints at the tracks' entries: 0.2 ms off; 3 px white noise added:
    6.2 ms off with partial windows, 1.1 ms with complete ones).

    ``quadratic``: a local quadratic fit with the same Gaussian weights instead of their mean
    (exact for constant acceleration: the mean flattens a displacement over a fraction of a
    frame by 1 - exp(-(sigma w)^2 / 2) for motion of w rad/frame, which biases an offset
    measured from displacements, timing_joint); the mean where the fit is singular."""
    F = X.shape[1]
    t, k, j = where
    half = int(np.ceil(KERNEL_REACH * sigma))
    base = np.floor(deltas).astype(np.int64)
    lo, hi = int(base.min()) - half, int(base.max()) + half + 1
    ms = np.arange(lo, hi + 1)
    frame = k[:, None] + ms[None]  # (N,M) the samples every delta may weigh
    inside = (frame >= 0) & (frame < F)
    G = X[t[:, None], np.clip(frame, 0, F - 1), j[:, None]]
    ok = inside & np.all(np.isfinite(G), axis=-1)
    G = np.where(ok[..., None], G, 0.0)
    W = np.exp(-0.5 * ((ms[None] - deltas[:, None]) / sigma) ** 2)  # (D,M)
    W[(ms[None] < base[:, None] - half) | (ms[None] > base[:, None] + half + 1)] = 0.0
    num = W @ G.transpose(1, 0, 2).reshape(len(ms), -1)  # (D,N*dim)
    den = W @ ok.T.astype(float)  # (D,N)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num.reshape(len(deltas), -1, X.shape[-1]) / den[..., None]
        if quadratic:
            out = _local_quadratic(W, ms[None] - deltas[:, None], G, ok, out)
    if complete:  # every sample the kernel weighs present
        gap = (W > 0).astype(float) @ (~ok).T.astype(float) > 0  # (D,N)
    else:  # only the two frames around k + delta
        col = base - lo
        gap = ~(ok[:, col].T & ok[:, col + 1].T)
    out[gap] = np.nan
    return out


def _local_quadratic(
    W: np.ndarray, u: np.ndarray, G: np.ndarray, ok: np.ndarray, mean: np.ndarray
) -> np.ndarray:
    """(D,N,3): the constant term of the weighted quadratic fit in u (D,M frames from the
    evaluation point) of the samples G (N,M,3) valid where ok (N,M), weights W (D,M); Cramer's
    rule on the 3x3 normal equations of every (delta, entry); ``mean`` where singular."""
    Gf = G.transpose(1, 0, 2).reshape(G.shape[1], -1)
    S = [(W * u**p) @ ok.T.astype(float) for p in range(5)]  # (D,N) moments
    T = [((W * u**p) @ Gf).reshape(W.shape[0], -1, G.shape[-1]) for p in range(3)]
    det = (
        S[0] * (S[2] * S[4] - S[3] ** 2)
        - S[1] * (S[1] * S[4] - S[2] * S[3])
        + S[2] * (S[1] * S[3] - S[2] ** 2)
    )
    c0, c1, c2 = (S[2] * S[4] - S[3] ** 2), (S[2] * S[3] - S[1] * S[4]), (S[1] * S[3] - S[2] ** 2)
    fit = (c0[..., None] * T[0] + c1[..., None] * T[1] + c2[..., None] * T[2]) / det[..., None]
    good = np.abs(det) > 1e-9 * np.maximum(S[0], 1e-300) ** 3
    return np.where(good[..., None], fit, mean)


def _residuals(
    P_c: np.ndarray, X: np.ndarray, U_c: np.ndarray, deltas: np.ndarray, complete: bool = True
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """(D,N,2) px: the N keypoints of camera c seen in U_c (T,F,J,2) minus the projections of
    the 3D tracks X (T,F,J,3) smoothed and evaluated at frame k + delta (kernel_tracks), for
    each of the D deltas (``complete``: kernel_tracks's); and where the N keypoints are
    (track, frame, joint)."""
    seen = np.all(np.isfinite(U_c), axis=-1)
    where = np.nonzero(seen)
    Xk = kernel_tracks(X, where, deltas, complete=complete)
    return _project(P_c, Xk) - U_c[seen], where


def truncation_px(
    P_c: np.ndarray, X: np.ndarray, U_c: np.ndarray, delta: float, complete: bool = True
) -> float:
    """px: the cap of camera c's squared errors: TRUNCATE_PX, or TRUNCATE_REL x the median
    error at ``delta`` frames when the keypoints are noisier."""
    e = np.linalg.norm(_residuals(P_c, X, U_c, np.array([delta]), complete)[0][0], axis=-1)
    e = e[np.isfinite(e)]
    return max(TRUNCATE_PX, TRUNCATE_REL * float(np.median(e))) if e.size else TRUNCATE_PX


def _scan(
    P_c: np.ndarray,
    X: np.ndarray,
    U_c: np.ndarray,
    deltas: np.ndarray,
    cap_px: float = TRUNCATE_PX,
    complete: bool = True,
) -> np.ndarray:
    """Mean truncated squared error (px^2, capped at cap_px^2) of camera c's keypoints U_c
    (T,F,J,2) against the 3D tracks X (T,F,J,3) at frame k + delta (_residuals), for every
    delta, over the terms defined at all of them (so that the costs compare the same
    observations)."""
    e2 = np.sum(_residuals(P_c, X, U_c, deltas, complete)[0] ** 2, axis=-1)
    common = np.all(np.isfinite(e2), axis=0)
    if not common.any():
        return np.full(len(deltas), np.inf)
    return np.mean(np.minimum(e2[:, common], cap_px**2), axis=1)


def offset_sd(
    P_c: np.ndarray,
    X: np.ndarray,
    U_c: np.ndarray,
    delta: float,
    cap_px: float,
    step: float = 0.05,
    complete: bool = True,
) -> float:
    """Standard error (frames) of camera c's offset ``delta`` (frames): the Gauss-Newton
    curvature of the capped cost (the keypoints' image speed px/frame, from a central
    difference of +-step frames) with a sandwich over tracks, whose errors are correlated (a
    track's detections share its pose errors and its wrong matches), not over keypoints."""
    r3, where = _residuals(P_c, X, U_c, np.array([delta - step, delta, delta + step]), complete)
    ok = np.all(np.isfinite(r3), axis=(0, 2))
    r, J = r3[1][ok], (r3[2] - r3[0])[ok] / (2 * step)
    keep = np.sum(r * r, axis=1) < cap_px**2
    H = float(np.sum(J[keep] ** 2))
    if H <= 0:
        return np.inf
    _, track = np.unique(where[0][ok][keep], return_inverse=True)
    g = np.bincount(track, np.sum(J[keep] * r[keep], axis=1))
    n = g.size
    return float(np.sqrt(np.sum(g**2) * n / max(n - 1, 1)) / H)


def _best_delta(P_c, X, U_c, centre: float, reach: float, complete: bool = True) -> tuple[float, float]:
    """Scan 0.2 frame steps over centre +- reach, a parabola through the best three, then a
    0.02 frame scan around it; the offset (frames) and its standard error (offset_sd).
    ``complete`` (kernel_tracks) for all but a scan beyond COMPLETE_SCAN_REACH."""
    cap = truncation_px(P_c, X, U_c, centre, complete)
    grid = centre + np.arange(-reach, reach + 1e-9, 0.2)
    costs = _scan(P_c, X, U_c, grid, cap, complete and reach <= COMPLETE_SCAN_REACH)
    if not np.isfinite(costs).any():
        return centre, np.inf
    k = int(np.argmin(costs))
    best = grid[k]
    if 0 < k < len(grid) - 1:
        c0, c1, c2 = costs[k - 1 : k + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best = grid[k] + 0.1 * (c0 - c2) / den
    fine = best + np.arange(-0.1, 0.1001, 0.02)
    fine_costs = _scan(P_c, X, U_c, fine, cap, complete)
    if np.isfinite(fine_costs).any():
        best = fine[int(np.argmin(fine_costs))]
    return float(best), offset_sd(P_c, X, U_c, float(best), cap, complete=complete)


def gauss_seidel_offsets(
    P: np.ndarray,
    U: np.ndarray,
    max_frames: float,
    rounds: int = 8,
    tol: float = 0.01,
    start: np.ndarray | None = None,
    complete: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """(C,) offsets in frames of the C > 2 cameras with projection matrices P (C,3,4) and 2D
    tracks U (C,T,F,J,2), relative to the median camera, and their (C,) standard errors
    (frames, each with the others fixed). Gauss-Seidel: each camera's offset is re-estimated
    against the others moved by their current offsets, until no offset changes by more than
    ``tol`` frames (the first round scans +-max_frames, later ones +-0.5 frame around the
    current value). ``start`` (C,) frames: offsets already close (from a previous rig),
    searched +-0.5 frame from the first round on: no full scan. ``complete``: the 3D tracks
    evaluated only where the kernel's window is complete (kernel_tracks). No significance
    test here (timing_joint.estimate_offsets applies them)."""
    C = P.shape[0]
    warm = start is not None
    delta = np.zeros(C) if start is None else np.asarray(start, float).copy()
    sd = np.full(C, np.inf)
    shifted = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)]) if warm else U.copy()
    for r in range(rounds):
        before = delta.copy()
        for c in range(C):
            others = [d for d in range(C) if d != c]
            X = triangulate(P[others], shifted[others])
            near = bool(r or warm)
            delta[c], sd[c] = _best_delta(
                P[c], X, U[c], delta[c] if near else 0.0, 0.5 if near else max_frames, complete
            )
            shifted[c] = shift_in_time(U[c], delta[c])
        delta -= np.median(delta)  # offsets are relative: keep the common part at 0
        shifted = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)])
        if np.max(np.abs(delta - before)) < tol:
            break
    return delta, sd


def _gain_z(gains: list[np.ndarray], groups: list[np.ndarray]) -> float:
    """z of the summed gains (px^2; one array per camera) with their standard error from the
    spread of the per-group sums (groups: one (camera, track) id per gain; a track's errors
    are correlated), 0 with fewer than two groups."""
    _, g = np.unique(np.concatenate(groups), return_inverse=True)
    per = np.bincount(g, np.concatenate(gains))
    if per.size < 2:
        return 0.0
    sd = np.sqrt(per.size) * np.std(per, ddof=1)
    return float(per.sum() / sd) if sd > 0 else np.inf


def _fit_gain_z(P: np.ndarray, U: np.ndarray, delta: np.ndarray, complete: bool = True) -> float:
    """The former joint test (time_test "interpolated"): how many standard errors the offsets
    ``delta`` (C,) frames improve the cross-view fit over a synchronised rig, each camera's
    capped squared errors against the others' triangulation from their 2D tracks moved to
    the reference times by linear interpolation (tracks.shift_in_time), the camera's own
    side evaluated by kernel_tracks; summed per (camera, track) (_gain_z). Interpolating
    noisy samples and flattening curved motion between frames differ from the estimator's
    kernel model, and on the bench's humanm3_4 s2 (true relative offsets -4.3 / +4.3 / -4.3
    / +14.2 ms) that left z = 1.9 at the estimated offsets: all zeroed, 14.2 ms off."""
    C = P.shape[0]
    moved = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)])
    gains, groups = [], []
    for c in range(C):
        others = [d for d in range(C) if d != c]
        caps, e2 = [], []
        for shifted, d in ((U, 0.0), (moved, delta[c])):
            X = triangulate(P[others], shifted[others])
            r, where = _residuals(P[c], X, U[c], np.array([d]), complete)
            e2.append(np.sum(r[0] ** 2, axis=-1))
            caps.append(truncation_px(P[c], X, U[c], d, complete))
        cap2 = max(caps) ** 2
        ok = np.isfinite(e2[0]) & np.isfinite(e2[1])
        gains.append(np.minimum(e2[0][ok], cap2) - np.minimum(e2[1][ok], cap2))
        groups.append(c * (U.shape[1] + 1) + where[0][ok])
    return _gain_z(gains, groups)


def _kernel_errors(P: np.ndarray, U: np.ndarray, delta: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
    """(2,N) px^2: camera c's N keypoints' squared reprojection errors against the other
    cameras' triangulation at c's own capture times, with all cameras synchronised (row 0)
    and at the offsets ``delta`` (C,) frames (row 1); and each keypoint's track (N,). Every
    other camera d's 2D tracks are smoothed by the Gaussian kernel in continuous time and
    evaluated at its frame position k + delta_c - delta_d (kernel_tracks, complete windows):
    the same smoothing at any sub-frame position, so no offset is favoured by less noise or
    less flattening, and camera c's keypoints are used as seen (no smoothing of its own)."""
    C = P.shape[0]
    seen = np.all(np.isfinite(U[c]), axis=-1)
    where = np.nonzero(seen)
    others = [d for d in range(C) if d != c]
    V = np.stack(
        [kernel_tracks(U[d], where, np.array([0.0, delta[c] - delta[d]])) for d in others]
    )  # (C-1,2,N,2)
    X = triangulate(P[others], V)  # (2,N,3)
    e2 = np.sum((_project(P[c], X) - U[c][seen]) ** 2, axis=-1)
    return e2, where[0]


def _fit_gain_z_kernel(P: np.ndarray, U: np.ndarray, delta: np.ndarray) -> float:
    """How many standard errors the offsets ``delta`` (C,) frames improve the cross-view fit
    over a synchronised rig (time_test "kernel", the default): each camera's capped squared
    errors against the other cameras' triangulation at its capture times (_kernel_errors),
    synchronised and at the offsets, on the keypoints defined in both, capped at the larger
    of the two caps (TRUNCATE_PX or TRUNCATE_REL x the median error); the gain summed per
    (camera, track) (_gain_z). Why a joint test besides each offset's own: an offset's
    standard error holds the other cameras fixed, and a rig can have a combination of
    offsets (opposite cameras shifted against each other) that the cross-view fit barely
    sees, along which Gauss-Seidel amplifies small biases. Bench (maem-calib-bench --frames
    60 --seeds 4, first estimate): humanm3_4 s0 / s2 (offsets) z = 6.4 / 5.3, the synchronised
    humanm3_4 s1 and ring5_h5 s2 (Gauss-Seidel at up to 3.3 / 0.6 ms) -0.8 / -0.7."""
    gains, groups = [], []
    for c in range(P.shape[0]):
        e2, track = _kernel_errors(P, U, delta, c)
        ok = np.all(np.isfinite(e2), axis=0)
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(np.sqrt(e2[:, ok]), axis=1) if ok.any() else np.zeros(2)
        cap2 = np.max(np.maximum(TRUNCATE_PX, TRUNCATE_REL * med)) ** 2
        gains.append(np.minimum(e2[0, ok], cap2) - np.minimum(e2[1, ok], cap2))
        groups.append(c * (U.shape[1] + 1) + track[ok])
    return _gain_z(gains, groups)


def _two_camera_offset(P: np.ndarray, U: np.ndarray, max_frames: float) -> np.ndarray:
    """Two cameras: the relative offset minimising the triangulation's reprojection error
    (camera 1 moved in time against camera 0), split evenly around 0."""
    grid = np.arange(-max_frames, max_frames + 1e-9, 0.1)

    def cost(d: float) -> float:
        moved = np.stack([U[0], shift_in_time(U[1], d)])
        X = triangulate(P, moved)
        e2 = np.sum((np.stack([_project(P[c], X) for c in range(2)]) - moved) ** 2, axis=-1)
        e2 = e2[np.isfinite(e2)]
        return float(np.mean(np.minimum(e2, TRUNCATE_PX**2))) if e2.size else np.inf

    costs = np.array([cost(d) for d in grid])
    d = float(grid[int(np.nanargmin(costs))]) if np.isfinite(costs).any() else 0.0
    fine = d + np.arange(-0.06, 0.0601, 0.01)
    d = float(fine[int(np.nanargmin([cost(x) for x in fine]))])
    return np.array([-d / 2, d / 2])
