"""Bundle adjustment of a camera rig: the one solver shared by the people and the board modes.

Interface (everything in SI units, world frame arbitrary, cameras OpenCV-style):

* :class:`BundleProblem` holds the unknowns' start values and the observations:

  - cameras: ``K`` (C,3,3) pinhole intrinsics of the image the observations live in (the
    RECTIFIED image of the frontend), world->camera ``R`` (C,3,3) and ``t`` (C,3) m;
  - points: ``points`` (P,3) world m. A point is either *free* (its own 3 unknowns; a
    person's joint at one frame) or *rigid*: ``point_object[p] = o >= 0`` puts it at
    ``object_R[o] @ model[p] + object_t[o]`` (a board corner; the board pose of each
    capture is 6 unknowns, the corner layout ``model`` (P,3) m in the board frame is fixed,
    so a board fixes the scale);
  - observations: ``obs_camera`` (M,), ``obs_point`` (M,), ``obs_uv`` (M,2) px, optional
    ``obs_weight`` (M,) (e.g. keypoint scores) and ``obs_group`` (M,) (e.g. the detection an
    observation belongs to: a group whose median residual is an outlier is rejected whole).

* :func:`bundle_adjust` (problem, :class:`BundleOptions`) -> :class:`BundleResult` with the
  refined R, t, focal scales, k1, K, dist, points, object poses, the inlier mask and per-observation
  residuals (px), and the per-camera 6x6 covariance of (rotation rad, centre m) if asked.

Gauge: the cameras listed in ``fixed_cameras`` keep their pose (default: camera 0). With free
points only, the overall scale is not observable; the damping keeps it where it starts (the
caller sets it, e.g. from metric skeletons). Refined intrinsics: a focal scale ``s`` (fx, fy,
skew times s) and a radial term ``k1`` on the normalised coordinates of the given image
(residual distortion of an already rectified image; 0 at the start); or, with
``BundleOptions.intrinsics``, any of fx fy cx cy (px) and the plumb_bob k1 k2 p1 p2 k3 of
``dist`` (C,5) on the observations' raw image (the board mode's one-run calibration: every
camera's lens refined from the shared frames, the board layout the known object). These are a
few more columns of each camera block, so the Schur structure is unchanged.

Solver: Levenberg-Marquardt on the normal equations with the structure (free points: 3x3
blocks; rigid objects: 6x6 blocks) eliminated by a Schur complement, an analytic Jacobian and
iteratively re-weighted robust losses with a wide-to-narrow schedule (Cauchy 50 px, Cauchy
20 px, soft-L1 5 px by default), then rejection of outlier observations and groups and a final
narrow pass. Why not ``scipy.optimize.least_squares(method='trf', jac_sparsity=...)`` (what
aniposelib's ``CameraGroup.bundle_adjust_iter`` uses): it finite-differences the Jacobian and
solves each step with LSMR over all (3 x points + 6 x cameras) unknowns; the reduced camera
system here is only (6..8 C)^2. scripts/bundle_vs_scipy.py measures both on one problem
(11,874 observations, 6 cameras, 1 px noise, 3 deg / 0.2 m start, 2-core machine, 2026-12-05):
same accuracy (0.023 deg, 0.7 cm), scipy 16 x the run time (0.97 s against 0.06 s); the
issue's experiment on real keypoints found scipy also unreliable from a rough start (soft_l1 out
of evaluations, Huber not moving) where an LM with a Schur complement converged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from .bundle_solver import (
    INTRINSIC_NAMES,
    NormalEquations,
    Observations,
    State,
    project,
    reduced_system,
    robust_rho,
    skew,
    solve_step,
)

__all__ = [
    "BundleProblem",
    "BundleOptions",
    "BundleResult",
    "bundle_adjust",
    "robust_rho",
    "DEFAULT_SCHEDULE",
    "WARM_SCHEDULE",
]

#: (loss name, scale px, max LM iterations) of each stage, from wide to narrow
DEFAULT_SCHEDULE: tuple[tuple[str, float, int], ...] = (
    ("cauchy", 50.0, 20),
    ("cauchy", 20.0, 20),
    ("soft_l1", 5.0, 40),
)
#: the last stage alone: for a start that is already close (a re-run after new observations)
WARM_SCHEDULE: tuple[tuple[str, float, int], ...] = (("soft_l1", 5.0, 40),)


@dataclass
class BundleProblem:
    """Start values and observations of a bundle adjustment (see the module docstring)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    obs_camera: np.ndarray
    obs_point: np.ndarray
    obs_uv: np.ndarray
    obs_weight: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    obs_group: np.ndarray | None = None
    point_object: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    model: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    object_R: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    object_t: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    focal_scale: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    k1: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__
    dist: np.ndarray = None  # type: ignore[assignment]  # None: the default, set in __post_init__

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, np.float64).reshape(-1, 3, 3)
        C = self.K.shape[0]
        self.R = np.asarray(self.R, np.float64).reshape(C, 3, 3)
        self.t = np.asarray(self.t, np.float64).reshape(C, 3)
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        P = self.points.shape[0]
        self.obs_camera = np.asarray(self.obs_camera, np.int64).ravel()
        self.obs_point = np.asarray(self.obs_point, np.int64).ravel()
        M = self.obs_camera.size
        self.obs_uv = np.asarray(self.obs_uv, np.float64).reshape(M, 2)
        self.obs_weight = (
            np.ones(M) if self.obs_weight is None else np.asarray(self.obs_weight, np.float64).reshape(M)
        )
        self.obs_group = None if self.obs_group is None else np.asarray(self.obs_group, np.int64).reshape(M)
        self.point_object = (
            np.full(P, -1, np.int64)
            if self.point_object is None
            else np.asarray(self.point_object, np.int64).reshape(P)
        )
        nobj = int(self.point_object.max(initial=-1)) + 1
        self.model = (
            np.zeros((P, 3)) if self.model is None else np.asarray(self.model, np.float64).reshape(P, 3)
        )
        self.object_R = (
            np.zeros((0, 3, 3))
            if self.object_R is None
            else np.asarray(self.object_R, np.float64).reshape(-1, 3, 3)
        )
        self.object_t = (
            np.zeros((0, 3))
            if self.object_t is None
            else np.asarray(self.object_t, np.float64).reshape(-1, 3)
        )
        self.focal_scale = (
            np.ones(C) if self.focal_scale is None else np.asarray(self.focal_scale, np.float64).reshape(C)
        )
        self.dist = np.zeros((C, 5)) if self.dist is None else np.asarray(self.dist, np.float64).reshape(C, 5)
        self.k1 = self.dist[:, 0].copy() if self.k1 is None else np.asarray(self.k1, np.float64).reshape(C)
        if self.object_R.shape[0] < nobj or self.object_t.shape[0] < nobj:
            raise ValueError(
                f"bundle problem: point_object refers to {nobj} objects, "
                f"object_R/object_t hold {self.object_R.shape[0]}/{self.object_t.shape[0]}"
            )
        if M and (self.obs_camera.min() < 0 or self.obs_camera.max() >= C):
            raise ValueError(f"bundle problem: obs_camera outside 0..{C - 1}")
        if M and (self.obs_point.min() < 0 or self.obs_point.max() >= P):
            raise ValueError(f"bundle problem: obs_point outside 0..{P - 1}")
        if not np.all(np.isfinite(self.obs_uv)):
            raise ValueError("bundle problem: obs_uv holds NaN or inf (drop unseen keypoints first)")
        free = self.point_object[self.obs_point] < 0
        key = self.obs_point[free] * C + self.obs_camera[free]
        if np.unique(key).size != key.size:
            raise ValueError("bundle problem: a free point is observed twice by one camera")

    @property
    def num_cameras(self) -> int:
        return int(self.K.shape[0])

    def world_points(self) -> np.ndarray:
        """(P,3) world m of every point (rigid ones placed by their object's pose)."""
        return self.world_points_of(self.object_R, self.object_t)

    def world_points_of(self, object_R: np.ndarray, object_t: np.ndarray) -> np.ndarray:
        """(P,3) world m: free points as given, rigid ones placed by the object poses given."""
        X = self.points.copy()
        rigid = self.point_object >= 0
        if rigid.any():
            o = self.point_object[rigid]
            X[rigid] = np.einsum("nij,nj->ni", object_R[o], self.model[rigid]) + object_t[o]
        return X


@dataclass
class BundleOptions:
    """How to solve. Scales are in px of the observations' image."""

    schedule: tuple[tuple[str, float, int], ...] = DEFAULT_SCHEDULE
    refine_focal: bool = False
    refine_k1: bool = False
    #: intrinsics refined per camera on the observations' (raw) image, any of
    #: bundle_solver.INTRINSIC_NAMES (fx fy cx cy k1 k2 p1 p2 k3); not with refine_focal /
    #: refine_k1 (the same unknowns on a rectified image)
    intrinsics: tuple[str, ...] = ()
    fixed_cameras: tuple[int, ...] = (0,)
    #: an observation is an outlier when its residual exceeds max(outlier_px, outlier_mads x
    #: the robust spread of all residuals); a group when its median residual does
    outlier_px: float = 10.0
    outlier_mads: float = 5.0
    reject_rounds: int = 2
    #: LM stops when the relative cost decrease of an accepted step is below this
    ftol: float = 1e-6
    #: ... or when the step moved no camera by more than this: rotation (rad), translation
    #: (relative to the median camera-to-point distance), focal scale and k1. The structure
    #: of a crowd converges far slower than the cameras (points still creep by millimetres
    #: after the rig has settled to 1e-4 deg), and the cost criterion waits for them
    xtol: float = 1e-5
    covariance: bool = False

    def __post_init__(self) -> None:
        unknown = set(self.intrinsics) - set(INTRINSIC_NAMES)
        if unknown:
            raise ValueError(
                f"bundle options: unknown intrinsics {sorted(unknown)} (expected "
                f"some of {' '.join(INTRINSIC_NAMES)})"
            )
        if self.intrinsics and (self.refine_focal or self.refine_k1):
            raise ValueError(
                "bundle options: intrinsics refine fx fy ... themselves; not with refine_focal / refine_k1"
            )


@dataclass
class BundleResult:
    """Refined unknowns (as in :class:`BundleProblem`), inlier mask (M,), residuals (M,2) px
    (projection - observation, NaN for points left out: fewer than 2 inlier cameras), LM
    iterations per stage, and, with ``BundleOptions.covariance``, ``camera_cov`` (C,6,6): the
    covariance of (rotation-vector perturbation rad, camera centre m) from the inverse reduced
    camera system scaled by the final residual variance (0 for fixed cameras)."""

    R: np.ndarray
    t: np.ndarray
    focal_scale: np.ndarray
    k1: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    points: np.ndarray
    object_R: np.ndarray
    object_t: np.ndarray
    inliers: np.ndarray
    residuals: np.ndarray
    iterations: list[int] = field(default_factory=list)
    camera_cov: np.ndarray | None = None

    @property
    def centers(self) -> np.ndarray:
        """(C,3) camera centres, world m."""
        return -np.einsum("cji,cj->ci", self.R, self.t)

    def errors(self) -> np.ndarray:
        """(M,) reprojection error px (NaN where not evaluated)."""
        return np.linalg.norm(self.residuals, axis=1)


# ---- the solver -----------------------------------------------------------------------------
def bundle_adjust(prob: BundleProblem, opts: BundleOptions | None = None) -> BundleResult:
    """Refine ``prob`` (see the module docstring): the robust schedule, then up to
    ``reject_rounds`` rounds of outlier rejection each followed by the schedule's last stage."""
    opts = opts or BundleOptions()
    # the dense products are small: one BLAS thread (threads only contend on a shared machine)
    with threadpool_limits(limits=1):
        return _bundle_adjust(prob, opts)


def _bundle_adjust(prob: BundleProblem, opts: BundleOptions) -> BundleResult:
    C = prob.num_cameras
    pose_free = np.ones(C, bool)
    pose_free[list(opts.fixed_cameras)] = False
    D = prob.dist.copy()
    D[:, 0] = prob.k1
    st = State(
        prob.R,
        prob.t,
        prob.focal_scale,
        prob.K,
        D,
        prob.points,
        prob.object_R,
        prob.object_t,
        opts.refine_focal,
        opts.refine_k1,
        opts.intrinsics,
    )
    # (C, dc) unknowns solved for: a fixed camera keeps its pose (the gauge), focal scale and
    # k1, not its lens: the board mode's intrinsics are refined for every camera
    free_cam = np.repeat(pose_free[:, None], st.dc, axis=1)
    free_cam[:, st.dc - len(st.intrinsics) :] = True
    active = _constrained(prob, np.ones(prob.obs_camera.size, bool))
    iterations = []
    for loss, scale, max_it in opts.schedule:
        st, n = _levenberg_marquardt(st, prob, active, loss, scale, max_it, free_cam, opts)
        iterations.append(n)
    loss, scale, max_it = opts.schedule[-1]
    for _ in range(opts.reject_rounds):
        keep = _reject_outliers(st, prob, active, opts)
        if np.array_equal(keep, active):
            break
        active = keep
        st, n = _levenberg_marquardt(st, prob, active, loss, scale, max_it, free_cam, opts)
        iterations.append(n)
    residuals = np.full((prob.obs_camera.size, 2), np.nan)
    ob = Observations(prob, _evaluable(prob, active))
    residuals[ob.idx] = _residuals(st, ob)
    points = st.X.copy()
    points[prob.point_object >= 0] = prob.world_points_of(st.oR, st.ot)[prob.point_object >= 0]
    solved = np.zeros(prob.points.shape[0], bool)
    solved[prob.obs_point[active]] = True
    points[~solved] = np.nan  # left out (fewer than two inlier cameras): not estimated
    result = BundleResult(
        R=st.R,
        t=st.t,
        focal_scale=st.s,
        k1=st.k1.copy(),
        K=st.K,
        dist=st.D,
        points=points,
        object_R=st.oR,
        object_t=st.ot,
        inliers=active,
        residuals=residuals,
        iterations=iterations,
    )
    if opts.covariance:
        result.camera_cov = _camera_covariance(st, prob, active, free_cam)
    return result


def _residuals(st: State, ob: Observations) -> np.ndarray:
    """(m,2) px residuals of the observations, in ``ob``'s order."""
    out = np.empty((len(ob), 2))
    for blk in ob.blocks:
        out[blk.sl] = project(st, ob, blk, False)
    return out


def _constrained(prob: BundleProblem, keep: np.ndarray) -> np.ndarray:
    """``keep`` less the observations of free points seen by fewer than two cameras and of
    objects with fewer than four observations (their structure block would be singular)."""
    keep = keep.copy()
    obj = prob.point_object[prob.obs_point]
    for _ in range(2):
        free = keep & (obj < 0)
        ncam = np.bincount(prob.obs_point[free], minlength=prob.points.shape[0])
        keep &= ~((obj < 0) & (ncam[prob.obs_point] < 2))
        rigid = keep & (obj >= 0)
        nobs = np.bincount(obj[rigid], minlength=max(1, prob.object_R.shape[0]))
        keep &= ~((obj >= 0) & (nobs[np.maximum(obj, 0)] < 4))
    return keep


def _evaluable(prob: BundleProblem, active: np.ndarray) -> np.ndarray:
    """Observations whose point (or object) is estimated by the active set."""
    obj = prob.point_object[prob.obs_point]
    solved_pt = np.zeros(prob.points.shape[0], bool)
    solved_pt[prob.obs_point[active]] = True
    solved_obj = np.zeros(max(1, prob.object_R.shape[0]), bool)
    solved_obj[obj[active & (obj >= 0)]] = True
    return np.where(obj >= 0, solved_obj[np.maximum(obj, 0)], solved_pt[prob.obs_point])


def _reject_outliers(st: State, prob: BundleProblem, active: np.ndarray, opts: BundleOptions) -> np.ndarray:
    """Active observations less those over the threshold and those of outlier groups."""
    ob = Observations(prob, active)
    err = np.linalg.norm(_residuals(st, ob), axis=1)
    if err.size == 0:
        return active
    # median of a 2D Gaussian error norm = 1.1774 sigma
    thr = max(opts.outlier_px, opts.outlier_mads * float(np.median(err)) / 1.1774)
    keep = active.copy()
    keep[ob.idx[err > thr]] = False
    if prob.obs_group is not None:
        groups, inv = np.unique(prob.obs_group[ob.idx], return_inverse=True)
        inv = inv.ravel()
        order = np.lexsort((err, inv))
        counts = np.bincount(inv, minlength=groups.size)
        starts = np.cumsum(counts) - counts
        med = 0.5 * (err[order[starts + (counts - 1) // 2]] + err[order[starts + counts // 2]])
        keep &= ~np.isin(prob.obs_group, groups[med > thr])
    return _constrained(prob, keep)


def _levenberg_marquardt(
    st: State,
    prob: BundleProblem,
    active: np.ndarray,
    loss: str,
    scale: float,
    max_it: int,
    free_cam: np.ndarray,
    opts: BundleOptions,
) -> tuple[State, int]:
    """Iteratively re-weighted LM on the active observations with one robust loss; returns
    the new state and the number of accepted steps."""
    ob = Observations(prob, active)
    if len(ob) == 0:
        return st, 0
    C = prob.num_cameras
    free_here = free_cam & (np.bincount(ob.cam, minlength=C) > 0)[:, None]

    def cost(state: State) -> float:
        r = _residuals(state, ob)
        return 0.5 * float(np.sum(ob.w * robust_rho(loss, np.einsum("ni,ni->n", r, r), scale)[0]))

    current, mu, accepted = cost(st), 1e-3, 0
    step_scale = np.ones(st.dc)
    step_scale[3:6] = _distance_scale(st, prob, ob)
    for i, name in enumerate(st.intrinsics):  # focal lengths and principal points: px
        if name[0] in "fc":
            step_scale[st.dc - len(st.intrinsics) + i] = float(np.median(st.K[:, 0, 0]))
    for _ in range(max_it):
        ne = NormalEquations(st, ob, loss, scale, C)
        new = None
        while mu < 1e10:
            step = solve_step(ne, mu, free_here)
            if step is not None:
                dcam, dpt, dobj = step
                cand = st.updated(
                    dcam, _scatter(dpt, ob.points, st.X.shape[0]), _scatter(dobj, ob.objects, st.oR.shape[0])
                )
                cand_cost = cost(cand)
                if np.isfinite(cand_cost) and cand_cost < current:
                    new = cand
                    break
            mu *= 4.0
        if new is None:
            break
        rel = (current - cand_cost) / max(current, 1e-300)
        st, current, accepted = new, cand_cost, accepted + 1
        mu = max(mu / 3.0, 1e-12)
        if rel < opts.ftol or np.all(np.abs(dcam) <= opts.xtol * step_scale):
            break
    return st, accepted


def _distance_scale(st: State, prob: BundleProblem, ob: Observations) -> float:
    """Median distance (world units) from the cameras to the points they observe."""
    X = st.X
    if len(st.oR):
        X = np.where((prob.point_object >= 0)[:, None], prob.world_points_of(st.oR, st.ot), X)
    centres = -np.einsum("cji,cj->ci", st.R, st.t)
    sample = slice(None, None, max(1, len(ob) // 4096))
    d = np.linalg.norm(X[ob.pt[sample]] - centres[ob.cam[sample]], axis=1)
    return float(np.median(d)) if d.size else 1.0


def _scatter(step: np.ndarray, index: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, step.shape[1]))
    out[index] = step
    return out


def _camera_covariance(
    st: State, prob: BundleProblem, active: np.ndarray, free_cam: np.ndarray
) -> np.ndarray:
    """(C,6,6) covariance of (rotation perturbation rad, centre m) per camera: the
    pseudo-inverse of the reduced camera system (a tiny damping keeps the structure blocks
    invertible; gauge directions such as a free-point problem's scale get no variance) times
    the weighted residual variance."""
    ob = Observations(prob, active)
    C = prob.num_cameras
    ne = NormalEquations(st, ob, "linear", 1.0, C)
    red = None if len(ob) == 0 else reduced_system(ne, 1e-9, free_cam)
    cov = np.zeros((C, 6, 6))
    if red is None:
        return np.full((C, 6, 6), np.nan)
    r = _residuals(st, ob)
    dof = max(1, 2 * len(ob) - int(free_cam.sum()) - 3 * ob.points.size - 6 * ob.objects.size)
    sigma2 = float(np.sum(ob.w * np.einsum("ni,ni->n", r, r))) / dof
    full = np.linalg.pinv(red[0], rcond=1e-10, hermitian=True) * sigma2
    dc = st.dc
    for c in np.flatnonzero(free_cam[:, 0]):
        blk = full[c * dc : c * dc + 6, c * dc : c * dc + 6]
        Rt = st.R[c].T
        T = np.zeros((6, 6))
        T[:3, :3] = np.eye(3)
        T[3:, :3] = -Rt @ skew(st.t[c])  # d centre / d rotation perturbation
        T[3:, 3:] = -Rt  # d centre / d t
        cov[c] = T @ blk @ T.T
    return cov
