"""Measure the shared bundle adjustment (core/calibrate/bundle.py: LM + Schur complement +
analytic Jacobian) against scipy.optimize.least_squares(method='trf', jac_sparsity=...) with a
finite-difference Jacobian (aniposelib's approach) on the same synthetic problem.

    .venv/bin/python scripts/bundle_vs_scipy.py [--points 2000] [--cameras 6] [--noise 1.0]

Prints run time and the worst camera rotation / centre error of both (the rig recovered up to
its scale gauge; camera 0 fixed in both).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from helpers_calibrate import rotation_angle_deg  # noqa: E402
from helpers_scene import CALIBRATION_RING, ring_rig  # noqa: E402

from maem_ros.core.calibrate.bundle import BundleOptions, BundleProblem, bundle_adjust  # noqa: E402


def _problem(points: int, cameras: int, noise: float, seed: int):
    rng = np.random.default_rng(seed)
    rig = ring_rig(cameras, height=4.0, jitter_seed=seed, **CALIBRATION_RING)
    X = np.column_stack([rng.uniform(-6, 6, points), rng.uniform(-4, 4, points), rng.uniform(0, 2, points)])
    cams, pts, uvs = [], [], []
    for c, cam in enumerate(rig):
        uv = cam.project_rectified(X)
        ok = np.all(np.isfinite(uv), 1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        cams.append(np.full(ok.sum(), c))
        pts.append(np.flatnonzero(ok))
        uvs.append(uv[ok] + rng.normal(0, noise, (ok.sum(), 2)))
    R0 = np.stack([Rotation.from_rotvec(rng.normal(0, np.radians(3), 3)).as_matrix() @ c.R for c in rig])
    t0 = np.stack([c.t + rng.normal(0, 0.2, 3) for c in rig])
    R0[0], t0[0] = rig[0].R, rig[0].t
    return rig, BundleProblem(K=np.stack([c.K for c in rig]), R=R0, t=t0,
                              points=X + rng.normal(0, 0.1, X.shape), obs_camera=np.concatenate(cams),
                              obs_point=np.concatenate(pts), obs_uv=np.concatenate(uvs))


def _errors(rig, R, centres) -> tuple[float, float]:
    s = np.linalg.norm(rig[1].center - rig[0].center) / np.linalg.norm(centres[1] - centres[0])
    rot = max(rotation_angle_deg(R[c], cam.R) for c, cam in enumerate(rig))
    cen = max(np.linalg.norm(centres[0] + s * (centres[c] - centres[0]) - cam.center)
              for c, cam in enumerate(rig))
    return rot, cen


def _scipy(prob: BundleProblem, loss_scale: float):
    C, P = prob.num_cameras, prob.points.shape[0]
    cam, pt = prob.obs_camera, prob.obs_point

    def unpack(x):
        rv = np.vstack([Rotation.from_matrix(prob.R[0]).as_rotvec(), x[:(C - 1) * 3].reshape(C - 1, 3)])
        t = np.vstack([prob.t[0], x[(C - 1) * 3:(C - 1) * 6].reshape(C - 1, 3)])
        return Rotation.from_rotvec(rv).as_matrix(), t, x[(C - 1) * 6:].reshape(P, 3)

    def fun(x):
        R, t, X = unpack(x)
        Xc = np.einsum("nij,nj->ni", R[cam], X[pt]) + t[cam]
        uv = np.einsum("nij,nj->ni", prob.K[cam, :2, :2], Xc[:, :2] / Xc[:, 2:]) + prob.K[cam, :2, 2]
        return (uv - prob.obs_uv).ravel()

    A = lil_matrix((2 * cam.size, (C - 1) * 6 + 3 * P), dtype=int)
    rows = np.arange(cam.size)
    for k in range(3):
        for r in (0, 1):
            moving = cam > 0
            A[2 * rows[moving] + r, (cam[moving] - 1) * 3 + k] = 1
            A[2 * rows[moving] + r, (C - 1) * 3 + (cam[moving] - 1) * 3 + k] = 1
            A[2 * rows + r, (C - 1) * 6 + pt * 3 + k] = 1
    x0 = np.concatenate([Rotation.from_matrix(prob.R[1:]).as_rotvec().ravel(), prob.t[1:].ravel(),
                         prob.points.ravel()])
    sol = least_squares(fun, x0, jac_sparsity=A, method="trf", loss="soft_l1", f_scale=loss_scale,
                        x_scale="jac", max_nfev=200)
    R, t, _ = unpack(sol.x)
    return R, -np.einsum("cji,cj->ci", R, t), sol.nfev


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--noise", type=float, default=1.0, help="px")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rig, prob = _problem(args.points, args.cameras, args.noise, args.seed)
    print(f"{prob.obs_camera.size} observations, {args.points} points, {args.cameras} cameras "
          f"(start: 3 deg, 0.2 m per camera)")
    with threadpool_limits(limits=1):
        t0 = time.perf_counter()
        res = bundle_adjust(prob, BundleOptions())
        t_lm = time.perf_counter() - t0
        t0 = time.perf_counter()
        R, centres, nfev = _scipy(prob, 5.0)
        t_sp = time.perf_counter() - t0
    print(f"LM+Schur (bundle.py): {t_lm:7.2f} s  max rotation error {_errors(rig, res.R, res.centers)[0]:.4f} deg"
          f"  max centre error {_errors(rig, res.R, res.centers)[1] * 100:.2f} cm")
    print(f"scipy trf jac_sparsity: {t_sp:7.2f} s  max rotation error {_errors(rig, R, centres)[0]:.4f} deg"
          f"  max centre error {_errors(rig, R, centres)[1] * 100:.2f} cm  ({nfev} evaluations)")
    print(f"time ratio scipy / LM: {t_sp / t_lm:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
