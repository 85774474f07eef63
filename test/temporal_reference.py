"""The track stage's straightforward implementation (a per-camera loop of small numpy calls,
as core/tracking/temporal.py had it before it was batched over cameras), kept here only as the reference
that test_temporal_equivalence.py compares the batched stage against, frame by frame."""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.association.gates import epipolar
from maem_ros.core.detections import FrameDetections, vertex_subset
from maem_ros.core.geometry.camera import fundamental_matrix
from maem_ros.core.geometry.multiview import reprojection_errors
from maem_ros.core.geometry.procrustes import pa_mpjpe_finite
from maem_ros.core.skeleton import joint_subset
from maem_ros.core.association.pipeline import associate
from maem_ros.core.tracking.temporal import _GATED, TemporalAssociator, keep_idx
from maem_ros.core.tracking.track_geometry import median_depth as _depth
from maem_ros.core.tracking.track_geometry import nanmedian as _nanmedian
from maem_ros.core.tracking.track_geometry import project as _project
from maem_ros.core.tracking.track_geometry import verify_clusters as _verify


class ReferenceTemporalAssociator(TemporalAssociator):
    """TemporalAssociator with steps 2-4 computed camera by camera and pair gate by pair gate,
    and step 5 given every detection left, whatever its score (associate leaves out those under
    tau_det itself)."""

    def _associate_rest(self, by_cam, keep, scored, used, body, out, stats) -> None:
        res = associate(self.rig, {self.rig.names[c]: by_cam[c].select(k) if used[c].any() else by_cam[c]
                                   for c, k in keep.items()}, self.params)
        for k, v in res.stats.items():
            stats.setdefault(k, v)
        new = [(np.stack([c.members[:, 0], keep_idx(keep, c.members)], axis=1), c.costs)
               for c in res.clusters]
        if new and body.size:
            self._attach(new, by_cam, body, out, stats)

    def _explain(self, by_cam: dict[int, FrameDetections], body: np.ndarray,
                 used: dict[int, np.ndarray], stats: dict[str, float],
                 light: bool = False) -> dict[int, list]:
        """Steps 2-4: detections explained by the tracks' predictions, verified; then once more
        against the projections of each verified cluster's own triangulation (this frame's
        estimate, tighter than the prediction: a view where the prediction was ambiguous
        between two people is re-assigned by the views that agree). The full step's reference
        only (the light step is the same code with two parts left out)."""
        assert not light, "the reference has no light step"
        tracks = self.tracker.tracks
        pred = np.stack([t.joints for t in tracks])  # (T,J,3)
        sig = np.sqrt(np.stack([np.trace(t.Pc[:3, :3]) / 3.0 for t in tracks]))  # (T,) m
        gate = np.stack([np.minimum(self.tp.gate_px + self.tp.gate_sigma * self._focal[c] * sig
                                    / _depth(self._P[c], pred), self.tp.gate_max_px)
                         for c in range(len(self.rig))], axis=1)  # (T,C) px
        cam, det, present, keep, X = self._assign_verify(by_cam, body, pred, gate)
        refit = keep.sum(1) >= 2
        if refit.any() and self.tp.refine_px > 0:
            gate = np.where(refit[:, None], self.tp.refine_px, gate)
            cam, det, present, keep, X = self._assign_verify(
                by_cam, body, np.where(refit[:, None, None], X, pred), gate)
        return self._take_explained(cam, det, present, keep, X,
                                    lambda c, d: by_cam[c].kpts2d[d][body], used, stats)

    def _assign_verify(self, by_cam: dict[int, FrameDetections], body: np.ndarray,
                       joints: np.ndarray, gate: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per camera, Hungarian assignment of detections to the tracks' skeletons joints (T,J,3)
        on the median 2D body-keypoint distance (px) under gate (T,C) px; then verification.
        Returns members padded to (T,M): cam, det, present, kept, and joints X (T,J,3)."""
        T = len(joints)
        cand = np.full((T, len(self.rig)), -1, np.int64)
        costs, gated = {}, {}  # camera -> (T,N) cost px, gated; N its valid detections
        for c, fd in by_cam.items():
            ok = np.flatnonzero(fd.scores >= self.params.tau_det)
            if ok.size == 0:
                continue
            uv, _ = _project(self._P[c], joints)  # (T,J,2)
            diff = np.linalg.norm(uv[:, None] - fd.kpts2d[ok][:, body][None], axis=-1)  # (T,N,J)
            costs[c] = _nanmedian(diff)  # (T,N)
            gated[c] = np.isfinite(costs[c]) & (costs[c] < gate[:, c, None])
        contested = {c: g & ((g.sum(1, keepdims=True) > 1) | (g.sum(0, keepdims=True) > 1))
                     for c, g in gated.items()}
        anchor = {}  # (track, camera) -> detection: its only gated one, gated for no other track
        for c, g in gated.items():
            ok = np.flatnonzero(by_cam[c].scores >= self.params.tau_det)
            for t in range(T):
                if g[t].sum() == 1 and not contested[c][t].any():
                    anchor[t, c] = int(ok[np.argmax(g[t])])
        for c, fd in by_cam.items():
            if c not in costs:
                continue
            ok = np.flatnonzero(fd.scores >= self.params.tau_det)
            cost, okc = costs[c], gated[c]
            if self.tp.pose_weight > 0:
                for t, n in zip(*np.nonzero(contested[c])):
                    others = [(c2, d2) for (t2, c2), d2 in anchor.items() if t2 == t and c2 != c]
                    if others:
                        pc = [self._pair_cost(by_cam, c, int(ok[n]), c2, d2) for c2, d2 in others]
                        extra = float(np.mean(pc))
                    else:
                        extra = self._pose_cost(np.ones((1, 1), bool), joints[t:t + 1],
                                                fd.kpts3d[ok[n:n + 1]][:, body])[0, 0]
                    cost[t, n] += self.tp.pose_weight * extra
            rows, cols = linear_sum_assignment(np.where(okc, cost, _GATED))
            real = okc[rows, cols]
            cand[rows[real], c] = ok[cols[real]]
        return self._verify_cand(by_cam, body, cand)

    def _verify_union(self, by_cam: dict[int, FrameDetections], body: np.ndarray,
                      both: np.ndarray) -> np.ndarray:
        """The verified members (K,2) of a track's cluster merged with a new one (both (M,2))."""
        cand = np.full((1, len(self.rig)), -1, np.int64)
        cand[0, both[:, 0]] = both[:, 1]
        cam, det, _, keep, _ = self._verify_cand(by_cam, body, cand)
        return np.stack([cam[0, keep[0]], det[0, keep[0]]], axis=1)

    def _verify_cand(self, by_cam: dict[int, FrameDetections], body: np.ndarray,
                     cand: np.ndarray) -> tuple[np.ndarray, ...]:
        """Verification of the candidates cand (T,C) (-1 = none). Returns members padded to
        (T,M): cam, det, present, kept, and joints X (T,J,3)."""
        T = len(cand)
        has = cand >= 0  # members padded to (T,M), in camera order
        M = max(int(has.sum(1).max()), 1)
        order = np.argsort(~has, axis=1, kind="stable")[:, :M]
        cam = np.take_along_axis(np.broadcast_to(np.arange(cand.shape[1]), cand.shape), order, 1)
        det = np.take_along_axis(cand, order, 1)
        present = det >= 0
        uv = np.full((T, M, body.size, 2), np.nan)
        for c, fd in by_cam.items():
            sel = present & (cam == c)
            uv[sel] = fd.kpts2d[det[sel]][:, body]
        passes = self._pair_gates(by_cam, cam, det, present)
        keep, X = _verify(self._P[cam], uv, present, passes, self.params.tau_verify,
                          self.params.min_support)
        return cam, det, present, keep, X

    @staticmethod
    def _pose_cost(okc: np.ndarray, joints: np.ndarray, kpts3d: np.ndarray) -> np.ndarray:
        """(T,N) PA-MPJPE (m) of each gated detection's 3D body pose aligned onto the track's
        skeleton; 0 where not gated or the track has unseen joints (no preference)."""
        out = np.zeros(okc.shape)
        t, n = np.nonzero(okc & np.isfinite(joints).all((1, 2))[:, None])
        if t.size:
            out[t, n] = np.nan_to_num(pa_mpjpe_finite(kpts3d[n], joints[t]))
        return out

    def _pair_cost(self, by_cam: dict[int, FrameDetections], c1: int, d1: int, c2: int,
                   d2: int) -> float:
        """m: the association's pair cost of two detections (cameras in either order), capped
        at tau_cost; tau_cost when the pair fails the pair gates or has too few joints."""
        (ca, da), (cb, db) = sorted([(c1, d1), (c2, d2)])
        cam, det = np.array([[ca, cb]]), np.array([[da, db]])
        _, cost = self._pair_tests(by_cam, cam, det, np.ones((1, 2), bool))
        cap = self.params.tau_cost if self.params.tau_cost > 0 else 1.0
        return float(min(cost[0], cap)) if np.isfinite(cost[0]) else cap

    def _pair_gates(self, by_cam: dict[int, FrameDetections], cam: np.ndarray, det: np.ndarray,
                    present: np.ndarray) -> np.ndarray:
        """(T,M,M) bool: member pairs of each candidate cluster passing the association's pair
        gates (bbox-centre reprojection, epipolar on mesh vertices or keypoints, the cost: PA-MPJPE
        of the lower camera's 3D pose aligned onto the other's plus cost_epipolar_weight per
        tau_mesh of the pair's mean epipolar distance, under tau_cost), the same tests
        (core.geometry.multiview, core.association.gates.epipolar, core.geometry.procrustes) the cross-view association applies, on
        the few pairs inside the tracks' clusters only."""
        T, M = present.shape
        a_idx, b_idx = np.triu_indices(M, 1)
        t, q = np.nonzero(present[:, a_idx] & present[:, b_idx])
        ok, cost = self._pair_tests(by_cam, cam, det, present)
        if self.params.tau_cost > 0:
            ok[ok] = cost[ok] < self.params.tau_cost  # NaN (too few joints) fails
        passes = np.zeros((T, M, M), bool)
        passes[t, a_idx[q], b_idx[q]] = passes[t, b_idx[q], a_idx[q]] = ok
        return passes

    def _pair_tests(self, by_cam: dict[int, FrameDetections], cam: np.ndarray, det: np.ndarray,
                    present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The member pairs of each candidate cluster (np.nonzero order): (S,) bool passing the
        bbox-centre reprojection and epipolar gates, and (S,) m their cost (PA-MPJPE of the
        lower camera's 3D pose aligned onto the other's plus cost_epipolar_weight per tau_mesh
        of the pair's mean epipolar distance; NaN where a gate failed)."""
        T, M = present.shape
        a_idx, b_idx = np.triu_indices(M, 1)
        both = present[:, a_idx] & present[:, b_idx]  # members sorted by camera: ca < cb
        t, q = np.nonzero(both)
        ma, mb = a_idx[q], b_idx[q]
        ca, cb, da, db = cam[t, ma], cam[t, mb], det[t, ma], det[t, mb]
        ok = np.ones(t.size, bool)
        epi = np.zeros(t.size)  # px, mean epipolar distance of the pairs that passed
        p = self.params
        if p.reproj_gate and t.size:
            uv = np.empty((t.size, 2, 2))
            for c, fd in by_cam.items():
                uv[ca == c, 0] = fd.centers[da[ca == c]]
                uv[cb == c, 1] = fd.centers[db[cb == c]]
            Ps = np.stack([self._P[ca], self._P[cb]], axis=1)
            ok &= reprojection_errors(Ps, uv, p.reproj_reduce) < p.tau_reproj_bbox
        if self.verify_epipolar != "none" and t.size:
            key = ca * len(self.rig) + cb
            for k in np.unique(key[ok]).tolist():  # one kernel call per camera pair
                s = np.flatnonzero(ok & (key == k))
                a, b = divmod(k, len(self.rig))
                xa, xb = self._points(by_cam[a]), self._points(by_cam[b])
                sums, used = epipolar.epipolar_sums(
                    xa, xb, fundamental_matrix(self.rig.cameras[a], self.rig.cameras[b]),
                    da[s], db[s], p.tau_mesh, symmetric=p.epipolar_distance == "symmetric",
                    early_exit=p.execution.early_exit, backend=p.execution.backend)
                ok[s] = sums < p.tau_mesh * used  # missing (NaN) points are not counted
                epi[s] = sums / np.maximum(used, 1)
        cost = np.full(t.size, np.nan)
        if ok.any():
            s = np.flatnonzero(ok)
            J = next(fd.num_joints for fd in by_cam.values() if fd.n)
            joints = joint_subset(p.cost_joints, J)
            X = np.empty((s.size, joints.size, 3))
            Y = np.empty_like(X)
            for c, fd in by_cam.items():
                X[ca[s] == c] = fd.kpts3d[da[s][ca[s] == c]][:, joints]
                Y[cb[s] == c] = fd.kpts3d[db[s][cb[s] == c]][:, joints]
            weight = p.cost_epipolar_weight / p.tau_mesh if self.verify_epipolar != "none" else 0
            cost[s] = pa_mpjpe_finite(X, Y) + weight * epi[s]
        return ok, cost

    def _points(self, fd: FrameDetections) -> np.ndarray:
        """The (N,n,2) px the verification's epipolar test compares: 2D keypoints, or the
        mesh vertices of the association's vertex subset."""
        if self.verify_epipolar == "sparse":
            return fd.kpts2d
        subset = vertex_subset(fd.num_vertices, self.params.vertex_stride,
                               self.params.vertex_count)
        return fd.verts2d if subset is None else fd.verts2d[:, subset]
