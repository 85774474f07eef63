"""Track-assisted association: match detections to existing 3D tracks first, run the full MAEM
cross-view association only on what is left (cross-view tracking, Chen et al. CVPR 2020).

Per synchronised frame set (all 2D in rectified px, 3D in world metres):

1. Predict every live track to the new stamp. State: a constant-velocity Kalman filter on the
   root (mean of the track's body joints; 6-state position/velocity, white-acceleration process
   noise ``accel_std`` m/s^2, measurement noise ``meas_std`` m) plus per-joint offsets from the
   root, exponentially smoothed (weight ``joint_alpha`` on the newest measurement). The predicted
   skeleton is root + offsets.
2. Gate every detection against every track's projected predicted body joints in its camera:
   the distance is the median over body joints of the 2D keypoint distance (px; the median
   ignores a grossly wrong limb); the gate is ``gate_px + gate_sigma * sigma_px``, capped at
   ``gate_max_px``, where sigma_px is the root's predicted position std projected at the
   track's depth in that camera (so it grows with every frame without support).
3. Per camera, Hungarian assignment of detections to tracks (gated pairs never match), so one
   detection explains at most one track, on that distance; a contested pair (two people
   overlapping in one image) adds ``pose_weight`` (px/m) times its mean association pair cost
   against the track's uncontested views this frame, else the PA-MPJPE of the detection's 3D
   body pose aligned onto the track's skeleton (core/tracking/contested.py).
   After verification (4) every track with a verified cluster is assigned once more against
   the projections of that cluster's own triangulation under ``refine_px``.
4. Geometric verification, batched over tracks, as the consistent clustering verifies a merge:
   every member must pass the association's pair gates (bbox-centre reprojection, epipolar
   distance of the association's ``epipolar_gate`` -- mesh vertices or 2D keypoints; another
   with ``verify_epipolar`` -- under ``tau_mesh``, the association's pair cost under
   ``tau_cost``) with at least ``min_support`` of the others, and reproject under the
   association's ``tau_verify`` px (median over the body joints DLT triangulated from all
   members); the worst member is dropped until all pass. Two members whose joints lie on
   average more than ``reid_m`` from the track's prediction (a narrow pair of rays, or a
   neighbour's detection) do not update the track: they are left to step 5, as with tracks
   off. A confirmed track is updated from ``min_track_views`` (2) views or more, fewer than
   ``k_min`` flagged ``FLAG_FEW_VIEWS``; with one view left it is kept alive by that view plus
   its prediction (``one_view``: the state moves to the points of the view's rays nearest the
   prediction; no cluster is emitted since one view triangulates nothing). A tentative track
   needs k_min views.
5. Detections not explained by any track go through ``associate`` (the full MAEM cross-view
   association, as a black box) on per-camera subsets; member indices are mapped back. Each new
   cluster is triangulated (body joints) and either merged into a track already supported this
   frame that it lies within ``reid_m`` of (if their cameras are disjoint), re-acquires an
   unsupported track within ``reid_m`` (Hungarian on 3D distance), or starts a tentative track.
6. A track is confirmed (gets an id) after ``confirm_hits`` supported frames and dies after
   ``max_misses`` consecutive frames without support. A stamp going backwards, or forward by
   more than ``max_gap_s``, ends all tracks first (ids are never reused).

``temporal = False`` is the per-frame paper pipeline: ``associate`` on everything, no track ids.

A *light* step (``step(..., light=True)``: the association node when a frame set waited for it
longer than a frame period, i.e. it is falling behind the camera rate) verifies a track's members
with the epipolar distance of their 2D body keypoints (``sparse``) instead of their mesh
vertices, leaves out the second assignment pass (step 3's ``refine_px``) and runs step 5 (new
people, tracks to re-acquire) only every ``light_new_every`` s (always without tracks); without
step 5 it reads no mesh vertex (:meth:`TemporalAssociator.associates_new` says so beforehand). A
node short of CPU catches up instead of skipping frame sets (costs: doc/performance_live.md).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.association.gates import PairGates
from maem_ros.core.association.params import AssociationParams
from maem_ros.core.association.pipeline import associate, score_counts
from maem_ros.core.detections import Cluster, FrameDetections
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.skeleton import body_joints
from maem_ros.core.tracking.contested import ContestSettings, contested_cost
from maem_ros.core.tracking.pair_costs import FramePairCosts, same_track_pairs
from maem_ros.core.tracking.temporal_params import TemporalParams
from maem_ros.core.tracking.track_filter import Track, Tracker3D
from maem_ros.core.tracking.track_geometry import (
    mean_distance,
    nanmedian,
    project,
    rays_nearest,
    triangulate_members,
    verify_clusters,
)

#: cluster flags (bit mask) of TemporalResult.flags
FLAG_TRACKED = 1  # members explained by a track's prediction (not by cross-view association)
FLAG_FEW_VIEWS = 2  # updated from fewer than k_min views (allowed for confirmed tracks only)
FLAG_ONE_VIEW = 4  # kept by one view + its prediction (internal: such clusters are not emitted)
_GATED = 1e9


@dataclass
class TemporalResult:
    """Clusters (members index the detections as given, ordered by first member), one track id
    per cluster (-1 = tentative track or temporal off), FLAG_* bits per cluster, stats."""

    clusters: list[Cluster]
    track_ids: np.ndarray
    flags: np.ndarray
    stats: dict[str, float] = field(default_factory=dict)


class _FrameView:
    """One frame set as the track stage reads it, built once per frame and shared by both
    assignment passes: every camera's detections padded to N rows (C = the rig's cameras;
    absent cameras and padding rows are NaN and invalid) and the frame set's pair decisions
    (FramePairCosts: each pair decided once)."""

    def __init__(
        self,
        stage: TemporalAssociator,
        by_cam: dict[int, FrameDetections],
        body: np.ndarray,
        light: bool = False,
    ):
        self.stage, self.by_cam = stage, by_cam
        C = len(stage.rig)
        self.n = max([fd.n for fd in by_cam.values()] + [1])
        self.kp2 = np.full((C, self.n, body.size, 2), np.nan)  # body keypoints, px
        self.kp3 = np.full((C, self.n, body.size, 3), np.nan)  # body joints, camera m
        self.centers = np.full((C, self.n, 2), np.nan)  # bbox centres, px
        self.valid = np.zeros((C, self.n), bool)  # a detection scored >= tau_det
        #: camera -> indices of its valid detections, for cameras with any
        self.ok: dict[int, np.ndarray] = {}
        for c, fd in by_cam.items():
            self.kp2[c, : fd.n] = fd.kpts2d[:, body]
            self.kp3[c, : fd.n] = fd.kpts3d[:, body]
            self.centers[c, : fd.n] = fd.centers
            ok = np.flatnonzero(fd.scores >= stage.params.tau_det)
            self.valid[c, ok] = True
            if ok.size:
                self.ok[c] = ok
        #: the frame set's pair decisions and costs (core/tracking/pair_costs.py)
        gates, epipolar = stage.verify_gates, stage.verify_epipolar
        if light:
            gates, epipolar = stage.light_gates, stage.light_epipolar
        self.costs = FramePairCosts(gates.frame_set(by_cam), by_cam, stage.params, epipolar, C, self.n)


# ---------------------------------------------------------------------------------------
# the stage
# ---------------------------------------------------------------------------------------
TEMPORAL_STAT_KEYS = (
    "tracks",
    "tracks_confirmed",
    "detections_explained",
    "detections_left",
    "tracks_supported",
    "tracks_few_views",
    "tracks_one_view",
    "tracks_two_view_jumps",
    "tracks_started",
    "tracks_reacquired",
    "tracks_merged",
    "tracks_ended",
    "track_resets",
    "verify_dropped",
    "light_steps",
    "new_deferred",
    "t_track_ms",
    "t_associate_ms",
)


class TemporalAssociator:
    """Stateful association: tracks first, ``associate`` on the rest (module docstring).

    One instance per stream; ``step`` must be called with the frame sets in stamp order (a stamp
    going backwards ends all tracks).
    """

    def __init__(self, rig: Rig, params: AssociationParams, temporal: TemporalParams):
        self.rig = rig
        self.params = params
        self.tp = temporal
        self.tracker = Tracker3D(temporal)
        self._P = np.stack([c.P for c in rig.cameras])
        #: the association's pair gates (frames prepared as they arrive: prepare), and the
        #: same gates with the verification's epipolar test (verify_epipolar)
        self.gates = PairGates(rig, params)
        self.verify_epipolar = (
            params.epipolar_gate if temporal.verify_epipolar == "association" else temporal.verify_epipolar
        )
        self.verify_gates = self.gates.with_epipolar_gate(self.verify_epipolar)
        #: a light step's verification: 2D keypoints instead of mesh vertices (module docstring)
        self.light_epipolar = "sparse" if self.verify_epipolar == "mesh" else self.verify_epipolar
        self.light_gates = self.gates.with_epipolar_gate(self.light_epipolar)
        self._contest = ContestSettings(params, temporal.pose_weight)
        self._centers = np.stack([c.center for c in rig.cameras])
        self._focal = np.array([0.5 * (c.K_rect[0, 0] + c.K_rect[1, 1]) for c in rig.cameras])
        self._last_stamp: int | None = None
        self._last_new: int | None = None  # stamp (ns) of the last frame set that ran step 5
        self.resets = 0

    def reset(self) -> None:
        """End every track; the next frame set starts from scratch."""
        self.tracker.reset()
        self._last_stamp = None
        self._last_new = None

    def associates_new(self, stamp_ns: int, light: bool) -> bool:
        """Whether :meth:`step` at ``stamp_ns`` runs step 5 (the cross-view association of the
        detections no track explains, which reads their mesh vertices): always in a full step,
        with ``temporal`` off, without tracks (or when this stamp ends them), and in a light step
        when the last set that ran it is ``light_new_every`` s old or more."""
        if not light or not self.tp.temporal or self._last_new is None or self._last_stamp is None:
            return True
        if not self.tracker.tracks or self._ends_tracks(int(stamp_ns)):
            return True
        return int(stamp_ns) - self._last_new >= self.tp.light_new_every * 1e9

    def _ends_tracks(self, stamp_ns: int) -> bool:
        """Whether a frame set at ``stamp_ns`` ends every track (a stamp back, or a gap)."""
        if self._last_stamp is None:
            return False
        dt = (stamp_ns - self._last_stamp) * 1e-9
        return dt < 0 or dt > self.tp.max_gap_s

    def step(
        self, frames: Mapping[str, FrameDetections], stamp_ns: int, light: bool = False
    ) -> TemporalResult:
        """Associate one synchronised frame set (keyed by camera name) at stamp_ns (int ns);
        ``light``: the light step of the module docstring (no effect with ``temporal`` off)."""
        if not self.tp.temporal:
            res = associate(self.rig, frames, self.params, self.gates)
            n = len(res.clusters)
            return TemporalResult(
                res.clusters, np.full(n, -1, np.int64), np.zeros(n, np.uint8), dict(res.stats)
            )
        t0 = time.perf_counter()
        stats: dict[str, float] = dict.fromkeys(TEMPORAL_STAT_KEYS, 0.0)
        new_now = self.associates_new(stamp_ns, light)
        self._advance(int(stamp_ns), stats)
        names = [n for n in self.rig.names if n in frames]
        by_cam = {self.rig.index(n): frames[n] for n in names}
        J = next((fd.num_joints for fd in by_cam.values() if fd.n), 0)
        body = np.asarray(body_joints(J), np.int64) if J else np.zeros(0, np.int64)
        used = {c: np.zeros(fd.n, bool) for c, fd in by_cam.items()}
        out: dict[int, list] = {}  # track key -> [members (M,2), costs (M,), flags]
        if self.tracker.tracks and J:
            out = self._explain(by_cam, body, used, stats, light)
            stats["light_steps"] = float(light)
        stats["t_track_ms"] = (time.perf_counter() - t0) * 1e3
        keep = {c: np.flatnonzero(~u) for c, u in used.items()}
        scored = {c: by_cam[c].scores[k] >= self.params.tau_det for c, k in keep.items()}
        stats["detections_left"] = float(sum(int(s.sum()) for s in scored.values()))
        if new_now:
            self._last_new = int(stamp_ns)
            self._associate_rest(by_cam, keep, scored, used, body, out, stats)
        else:
            stats["new_deferred"] = 1.0
        self._age(out, stats)
        return self._result(out, stats, t0)

    def _associate_rest(
        self,
        by_cam: dict[int, FrameDetections],
        keep: dict[int, np.ndarray],
        scored: dict[int, np.ndarray],
        used: dict[int, np.ndarray],
        body: np.ndarray,
        out: dict[int, list],
        stats: dict[str, float],
    ) -> None:
        """Step 5: ``associate`` on the detections no track explained (``keep``, per camera;
        ``scored``: which of them scored tau_det or more), its new clusters attached to tracks
        or started as tracks (module docstring)."""
        t1 = time.perf_counter()
        # a camera none of whose detections a track explained goes in as given (no copy of its
        # vertex arrays); the others as the subset of what is left that scored tau_det or more
        # (few once tracks run; below it a detection takes no part in associate)
        given = {c: k[scored[c]] if used[c].any() else k for c, k in keep.items()}
        subset = {
            c: self.gates.select(by_cam[c], k) if used[c].any() else by_cam[c] for c, k in given.items()
        }
        res = associate(self.rig, {self.rig.names[c]: f for c, f in subset.items()}, self.params, self.gates)
        left, kept = [k.size for k in keep.values()], [int(s.sum()) for s in scored.values()]
        res.stats.update(score_counts(left, kept))  # as if every detection left had gone in
        stats["t_associate_ms"] = (time.perf_counter() - t1) * 1e3
        for k, v in res.stats.items():
            stats.setdefault(k, v)
        new = [
            (np.stack([c.members[:, 0], keep_idx(given, c.members)], axis=1), c.costs) for c in res.clusters
        ]
        if new and body.size:
            self._attach(new, by_cam, body, out, stats)

    # -- steps ---------------------------------------------------------------------------
    def _advance(self, stamp_ns: int, stats: dict[str, float]) -> None:
        if self._ends_tracks(stamp_ns):
            self.tracker.reset()
            self.resets += 1
            stats["track_resets"] = 1.0
        elif self._last_stamp is not None:
            self.tracker.predict((stamp_ns - self._last_stamp) * 1e-9)
        self._last_stamp = stamp_ns

    def _explain(
        self,
        by_cam: dict[int, FrameDetections],
        body: np.ndarray,
        used: dict[int, np.ndarray],
        stats: dict[str, float],
        light: bool = False,
    ) -> dict[int, list]:
        """Steps 2-4: detections explained by the tracks' predictions, verified; then (unless
        ``light``) once more against the projections of each verified cluster's own
        triangulation (this frame's estimate, tighter than the prediction: a view where the
        prediction was ambiguous between two people is re-assigned by the views that agree)."""
        tracks = self.tracker.tracks
        view = _FrameView(self, by_cam, body, light)
        pred = np.stack([t.joints for t in tracks])  # (T,J,3)
        sig = np.sqrt(np.stack([t.Pc[0, 0] + t.Pc[1, 1] + t.Pc[2, 2] for t in tracks]) / 3.0)
        _, z = project(self._P[:, None, None], pred[None])  # (C,T,J) m, all cameras at once
        depth = nanmedian(np.where(z > 0, z, np.nan))  # (C,T)
        gate = np.minimum(
            self.tp.gate_px + self.tp.gate_sigma * self._focal[:, None] * sig / depth, self.tp.gate_max_px
        ).T  # (T,C) px
        cand = self._assign(view, pred, gate)
        cam, det, present, keep, X = self._verify_candidates(view, cand)
        refit = keep.sum(1) >= 2
        if refit.any() and self.tp.refine_px > 0 and not light:
            gate = np.where(refit[:, None], self.tp.refine_px, gate)
            again = self._assign(view, np.where(refit[:, None, None], X, pred), gate)
            if not np.array_equal(again, cand):  # the same candidates verify the same way
                cam, det, present, keep, X = self._verify_candidates(view, again)
        return self._take_explained(cam, det, present, keep, X, lambda c, d: view.kp2[c, d], used, stats)

    def _take_explained(
        self,
        cam: np.ndarray,
        det: np.ndarray,
        present: np.ndarray,
        keep: np.ndarray,
        X: np.ndarray,
        body_kpts: Callable[[int, int], np.ndarray],
        used: dict[int, np.ndarray],
        stats: dict[str, float],
    ) -> dict[int, list]:
        """Update every track from its verified members (padded (T,M) cam, det, present, keep;
        joints X (T,J,3)), or from one view and its prediction; mark the members used.
        body_kpts(c, d) -> (J,2) px body keypoints of detection d in camera c. Returns track key
        -> [members, costs, flags]."""
        tracks = self.tracker.tracks
        stats["verify_dropped"] = float((present & ~keep).sum())
        jumped = self._two_view_jumps(keep, X)
        stats["tracks_two_view_jumps"] = float(jumped.sum())
        out: dict[int, list] = {}
        updated: list[int] = []  # tracks updated from their verified members, batched below
        for i, t in enumerate(tracks):  # one iteration per person
            if jumped[i]:  # left to the cross-view association, as with tracks off
                continue
            n = int(keep[i].sum())
            need = self.tp.min_track_views if t.id >= 0 else self.params.k_min
            if n >= max(need, 2):
                members = np.stack([cam[i, keep[i]], det[i, keep[i]]], axis=1)
                updated.append(i)
                few = n < self.params.k_min
                stats["tracks_few_views"] += few
                out[t.key] = [members, np.full(n, np.nan), FLAG_TRACKED | (FLAG_FEW_VIEWS if few else 0)]
            elif t.id >= 0 and present[i].any() and self.tp.one_view:
                c, d = self._one_view(present[i], keep[i], cam[i], det[i])
                self.tracker.update(
                    t,
                    rays_nearest(self._P[c], self._centers[c], body_kpts(c, d), t.joints),
                    meas_std=self.tp.one_view_std,
                )
                stats["tracks_one_view"] += 1
                out[t.key] = [
                    np.array([[c, d]]),
                    np.full(1, np.nan),
                    FLAG_TRACKED | FLAG_FEW_VIEWS | FLAG_ONE_VIEW,
                ]
            else:
                continue
            for c, d in out[t.key][0].tolist():
                used[c][d] = True
        self.tracker.update_many([tracks[i] for i in updated], X[updated])
        stats["detections_explained"] = float(sum(u.sum() for u in used.values()))
        return out

    def _two_view_jumps(self, keep: np.ndarray, X: np.ndarray) -> np.ndarray:
        """(T,) bool: tracks whose verified cluster has two views (keep (T,M)) and whose joints
        X (T,J,3) lie on average more than ``reid_m`` from the track's prediction. Two views at
        a narrow angle triangulate metres off along the rays, and a detection the prediction
        proposed may be a neighbour's; either way such an update is not trusted: its detections
        go through the cross-view association like any unexplained detection."""
        two = keep.sum(1) == 2
        if not two.any():
            return two
        pred = np.stack([t.joints for t in self.tracker.tracks])  # (T,J,3)
        both = np.isfinite(pred).all(-1) & np.isfinite(X).all(-1)
        with np.errstate(invalid="ignore"):
            d = np.where(both, np.linalg.norm(pred - X, axis=-1), 0.0).sum(1)
        return two & (both.sum(1) > 0) & (d > self.tp.reid_m * np.maximum(both.sum(1), 1))

    def _assign(self, view: _FrameView, joints: np.ndarray, gate: np.ndarray) -> np.ndarray:
        """Per camera, Hungarian assignment of detections to the tracks' skeletons joints (T,J,3)
        on the median 2D body-keypoint distance (px) under gate (T,C) px. The distances of
        every track to every detection of every camera are one batched computation
        (detections padded per camera); only the assignment runs per camera. Returns the
        candidate detection (T,C) of each track in each camera (-1 = none)."""
        T, C = len(joints), len(self.rig)
        uv, _ = project(self._P[:, None, None], joints[None])  # (C,T,J,2)
        diff = np.linalg.norm(uv[:, :, None] - view.kp2[:, None], axis=-1)  # (C,T,N,J)
        cost = nanmedian(diff)  # (C,T,N)
        okc = view.valid[:, None] & np.isfinite(cost) & (cost < gate.T[:, :, None])
        # every pair the contested order and the verification may ask about, decided together
        view.costs.get(*same_track_pairs(okc))
        # contested candidates (two people close in one image) ordered by the track's other
        # views this frame, else by pose (core/tracking/contested.py)
        cost = cost + contested_cost(self._contest, view, okc, joints)
        cand = np.full((T, C), -1, np.int64)
        for c, ok in view.ok.items():  # one Hungarian per camera
            gated = okc[c][:, ok]
            rows, cols = linear_sum_assignment(np.where(gated, cost[c][:, ok], _GATED))
            real = gated[rows, cols]
            cand[rows[real], c] = ok[cols[real]]
        return cand

    def _verify_candidates(self, view: _FrameView, cand: np.ndarray) -> tuple[np.ndarray, ...]:
        """Verification of the candidates (T,C) (module docstring, step 4). Returns members
        padded to (T,M): cam, det, present, kept, and joints X (T,J,3)."""
        T, C = cand.shape
        has = cand >= 0  # members padded to (T,M), in camera order
        M = max(int(has.sum(1).max()), 1)
        order = np.argsort(~has, axis=1, kind="stable")[:, :M]
        cam = np.take_along_axis(np.broadcast_to(np.arange(C), cand.shape), order, 1)
        det = np.take_along_axis(cand, order, 1)
        present = det >= 0
        uv = np.where(present[:, :, None, None], view.kp2[cam, np.maximum(det, 0)], np.nan)
        passes = self._pair_gates(view, cam, det, present)
        keep, X = verify_clusters(
            self._P[cam], uv, present, passes, self.params.tau_verify, self.params.min_support
        )
        return cam, det, present, keep, X

    def _pair_gates(
        self, view: _FrameView, cam: np.ndarray, det: np.ndarray, present: np.ndarray
    ) -> np.ndarray:
        """(T,M,M) bool: member pairs of each candidate cluster passing the association's pair
        gates and pair cost (core/tracking/pair_costs.py: pairs already decided this frame set
        are looked up)."""
        T, M = present.shape
        a_idx, b_idx = np.triu_indices(M, 1)
        both = present[:, a_idx] & present[:, b_idx]  # members sorted by camera: ca < cb
        t, q = np.nonzero(both)
        ma, mb = a_idx[q], b_idx[q]
        ok = view.costs.get(cam[t, ma], cam[t, mb], det[t, ma], det[t, mb])[0]
        passes = np.zeros((T, M, M), bool)
        passes[t, ma, mb] = passes[t, mb, ma] = ok
        return passes

    @staticmethod
    def _one_view(present: np.ndarray, keep: np.ndarray, cam: np.ndarray, det: np.ndarray) -> tuple[int, int]:
        """The single view left: the verified one if any, else the first candidate."""
        k = int(np.flatnonzero(keep if keep.any() else present)[0])
        return int(cam[k]), int(det[k])

    def _attach(
        self,
        new: list[tuple[np.ndarray, np.ndarray]],
        by_cam: dict[int, FrameDetections],
        body: np.ndarray,
        out: dict[int, list],
        stats: dict[str, float],
    ) -> None:
        """Step 5: each new (members, costs) cluster merges into a track supported this frame
        (the union verified as the track's own candidates are), re-acquires an unsupported
        track, or starts a tentative one."""
        joints = self._triangulate([m for m, _ in new], by_cam, body)  # (K,J,3)
        tracks = self.tracker.tracks
        taken = np.zeros(len(new), bool)
        for group, merge in (
            ([t for t in tracks if t.key in out], True),
            ([t for t in tracks if t.key not in out], False),
        ):
            if not group or taken.all():
                continue
            d = mean_distance(np.stack([t.joints for t in group]), joints)  # (G,K)
            d[:, taken] = np.inf
            ok = np.isfinite(d) & (d < self.tp.reid_m)
            rows, cols = linear_sum_assignment(np.where(ok, d, _GATED))
            for r, k in zip(rows.tolist(), cols.tolist()):  # one iteration per person
                if not ok[r, k]:
                    continue
                t, (members, costs) = group[r], new[k]
                taken[k] = True
                if merge:
                    stats["tracks_merged"] += 1
                    merged = self._merge(t, out[t.key], members, costs, joints[k], by_cam, body, stats)
                    if merged is not None:
                        out[t.key] = merged
                else:
                    self.tracker.update(t, joints[k])
                    out[t.key] = [members, costs, 0]
                    stats["tracks_reacquired"] += 1
        for k in np.flatnonzero(~taken):
            t = self.tracker.start(joints[k])
            out[t.key] = [new[k][0], new[k][1], 0]
            stats["tracks_started"] += 1

    def _merge(
        self,
        t: Track,
        old: list,
        members: np.ndarray,
        costs: np.ndarray,
        joints: np.ndarray,
        by_cam: dict[int, FrameDetections],
        body: np.ndarray,
        stats: dict[str, float],
    ) -> list | None:
        """The entry [members, costs, flags] of track t (its entry this frame ``old``) merged with
        a new cross-view cluster (members, costs; body joints (J,3)) lying within reid_m of it,
        or None to keep ``old``. The union is verified as the track's own candidates are
        (:meth:`_verify_union`); when it verifies fewer members than one part alone (a
        verify_epipolar stricter than the association's gate, or two parts that are not one
        person), the larger part stands alone."""
        if np.intersect1d(old[0][:, 0], members[:, 0]).size:
            if old[2] & FLAG_ONE_VIEW:  # the cross-view cluster beats one view
                self.tracker.update(t, joints)
                return [members, costs, 0]
            return None  # else the same person twice in a camera: the track's wins
        union = np.concatenate([old[0], members])
        both = self._verify_union(by_cam, body, union)
        part = max(len(old[0]), len(members))
        stats["verify_dropped"] += float(len(union) - max(len(both), part))
        if len(both) < part:
            if len(members) <= len(old[0]):
                return None  # the track's cluster stays
            if old[2] & FLAG_ONE_VIEW:
                self.tracker.update(t, joints)
            return [members, costs, 0]
        few = FLAG_FEW_VIEWS if len(both) < self.params.k_min else 0
        return [both, np.full(len(both), np.nan), (old[2] & ~FLAG_FEW_VIEWS & ~FLAG_ONE_VIEW) | few]

    def _verify_union(
        self, by_cam: dict[int, FrameDetections], body: np.ndarray, both: np.ndarray
    ) -> np.ndarray:
        """The verified members (K,2) (camera, detection; camera order) of a track's cluster
        merged with a new cluster of other cameras (both (M,2)). Each part was verified alone,
        their union was not: a view consistent with one part (e.g. a body mixed from two
        overlapping people, 40+ px from the other part's rays) is dropped here as the track's
        verification or the consistent clustering's merge check would drop it."""
        cand = np.full((1, len(self.rig)), -1, np.int64)
        cand[0, both[:, 0]] = both[:, 1]
        # a view of its own (merges are rare: the pair gates of the track stage's are not kept)
        cam, det, _, keep, _ = self._verify_candidates(_FrameView(self, by_cam, body), cand)
        return np.stack([cam[0, keep[0]], det[0, keep[0]]], axis=1)

    def _triangulate(
        self, clusters: list[np.ndarray], by_cam: dict[int, FrameDetections], body: np.ndarray
    ) -> np.ndarray:
        """(K,J,3) DLT body joints of clusters (no member dropped; associate verified them)."""
        K, M = len(clusters), max(len(m) for m in clusters)
        cam = np.zeros((K, M), np.int64)
        present = np.zeros((K, M), bool)
        uv = np.full((K, M, body.size, 2), np.nan)
        for k, m in enumerate(clusters):  # one row per person
            cam[k, : len(m)] = m[:, 0]
            present[k, : len(m)] = True
            for j, (c, d) in enumerate(m.tolist()):
                uv[k, j] = by_cam[c].kpts2d[d][body]
        X, _ = triangulate_members(self._P[cam], uv, present)
        return X

    def _age(self, out: dict[int, list], stats: dict[str, float]) -> None:
        alive = []
        for t in self.tracker.tracks:
            if t.key not in out:
                t.misses += 1
            if t.misses <= self.tp.max_misses and (t.id >= 0 or t.misses == 0):
                alive.append(t)  # a tentative track without support is dropped at once
            else:
                stats["tracks_ended"] += 1
        self.tracker.tracks = alive
        stats["tracks"] = float(len(alive))
        stats["tracks_confirmed"] = float(sum(t.id >= 0 for t in alive))
        stats["tracks_supported"] = float(len(out))

    def _result(self, out: dict[int, list], stats: dict[str, float], t0: float) -> TemporalResult:
        """Clusters of >= 2 views (one view triangulates nothing), ordered by first member."""
        ids = {t.key: t.id for t in self.tracker.tracks}
        rows = sorted(
            ((m, c, key, f) for key, (m, c, f) in out.items() if len(m) >= 2),
            key=lambda r: tuple(r[0][0].tolist()),
        )
        clusters = [Cluster(members=m, costs=c) for m, c, _, _ in rows]
        track_ids = np.array([ids.get(key, -1) for _, _, key, _ in rows], np.int64)
        flags = np.array([f for _, _, _, f in rows], np.uint8)
        stats["clusters"] = float(len(clusters))
        stats["t_total_ms"] = (time.perf_counter() - t0) * 1e3
        return TemporalResult(clusters, track_ids, flags, stats)


def keep_idx(keep: dict[int, np.ndarray], members: np.ndarray) -> np.ndarray:
    """Map members' detection indices in the per-camera subsets back to the indices as given."""
    return np.array([keep[int(c)][int(d)] for c, d in members.tolist()], np.int64)
