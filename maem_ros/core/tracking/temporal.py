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
   detection explains at most one track, on that distance plus ``pose_weight`` (px/m) times
   the PA-MPJPE of the detection's 3D body pose aligned onto the track's skeleton (two people
   overlapping in one image are told apart by their poses, as the cross-view cost does).
   After verification (4) every track with a verified cluster is assigned once more against
   the projections of that cluster's own triangulation under ``refine_px``.
4. Geometric verification, batched over tracks, as the consistent clustering verifies a merge:
   every member must pass the association's pair gates (bbox-centre reprojection, epipolar
   distance of the 2D keypoints, or of the mesh with ``verify_epipolar: mesh``, under
   ``tau_mesh``, PA-MPJPE under ``tau_cost``) with at least ``min_support`` of the others,
   and reproject under the association's ``tau_verify`` px (median over the body joints DLT
   triangulated from all members); the worst member is dropped until all pass. A confirmed
   track is updated from ``min_track_views`` (2) views or more, fewer than ``k_min`` flagged
   ``FLAG_FEW_VIEWS``; with one view left it is kept alive by that view plus its prediction
   (``one_view``: the state moves to the points of the view's rays nearest the prediction; no
   cluster is emitted since one view triangulates nothing). A tentative track needs k_min views.
5. Detections not explained by any track go through ``associate`` (the full MAEM cross-view
   association, as a black box) on per-camera subsets; member indices are mapped back. Each new
   cluster is triangulated (body joints) and either merged into a track already supported this
   frame that it lies within ``reid_m`` of (if their cameras are disjoint), re-acquires an
   unsupported track within ``reid_m`` (Hungarian on 3D distance), or starts a tentative track.
6. A track is confirmed (gets an id) after ``confirm_hits`` supported frames and dies after
   ``max_misses`` consecutive frames without support. A stamp going backwards, or forward by
   more than ``max_gap_s``, ends all tracks first (ids are never reused).

``temporal = False`` is the per-frame paper pipeline: ``associate`` on everything, no track ids.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment

from maem_ros.core.association.pipeline import AssociationParams, associate, screen_levels, screen_subsets
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.detections import Cluster, FrameDetections
from maem_ros.core.association.gates import epipolar
from maem_ros.core.geometry.multiview import dlt, reprojection_errors
from maem_ros.core.intsets import sorted_unique
from maem_ros.core.paramspec import Params, param
from maem_ros.core.geometry.procrustes import pa_mpjpe_finite
from maem_ros.core.skeleton import body_joints, joint_subset

#: cluster flags (bit mask) of TemporalResult.flags
FLAG_TRACKED = 1  # members explained by a track's prediction (not by cross-view association)
FLAG_FEW_VIEWS = 2  # updated from fewer than k_min views (allowed for confirmed tracks only)
FLAG_ONE_VIEW = 4  # kept by one view + its prediction (internal: such clusters are not emitted)
_GATED = 1e9
#: epipolar test inside a track's cluster: 2D keypoints (default: on the simulator as accurate as
#: the mesh for clusters the prediction already proposes, at a fraction of the cost), the mesh
#: vertices (as the cross-view association), or none
VERIFY_EPIPOLAR = ("sparse", "mesh", "none")


@dataclass
class TemporalParams(Params):
    """Tracking stage of the association node (px, m, s, frames; module docstring); one field =
    one parameter of the association node (core/paramspec.py)."""

    temporal: bool = param(True, "track-assisted association (off = the per-frame paper "
                                 "pipeline, no track ids)")
    confirm_hits: int = param(3, "supported frames before a track gets an id", minimum=1)
    max_misses: int = param(10, "frames a track survives without support", minimum=0)
    max_gap_s: float = param(1.0, "s, a forward stamp jump beyond this ends all tracks",
                             minimum=0.0, exclusive_minimum=True)
    gate_px: float = param(25.0, "px, base gate of a detection's body keypoints vs a track's "
                                 "projected predicted joints (median distance)", minimum=0.0,
                           exclusive_minimum=True)
    gate_sigma: float = param(3.0, "gate growth per projected root std (px per px)",
                              minimum=0.0)
    gate_max_px: float = param(80.0, "px, cap of the track gate", minimum=0.0,
                               exclusive_minimum=True)
    refine_px: float = param(20.0, "px, gate of the second assignment against each verified "
                                   "cluster's own triangulation (0 = off)", minimum=0.0)
    pose_weight: float = param(100.0, "px per m of 3D-pose PA-MPJPE (detection vs track) added "
                                      "to the assignment cost", minimum=0.0)
    min_track_views: int = param(2, "views a confirmed track may be updated from (below k_min: "
                                    "flagged)", minimum=2)
    one_view: bool = param(True, "keep a confirmed track alive on one view + its prediction")
    one_view_std: float = param(0.3, "m, root measurement std of a one-view update",
                                minimum=0.0, exclusive_minimum=True)
    verify_epipolar: str = param("sparse", "epipolar test inside a track's cluster: 2D keypoints "
                                           "(sparse), mesh vertices or none",
                                 choices=VERIFY_EPIPOLAR)
    reid_m: float = param(0.5, "m, a new cluster this close to a track re-acquires / merges it",
                          minimum=0.0, exclusive_minimum=True)
    accel_std: float = param(4.0, "m/s^2, process noise of the root Kalman filter", minimum=0.0,
                             exclusive_minimum=True)
    meas_std: float = param(0.03, "m, root measurement std", minimum=0.0,
                            exclusive_minimum=True)
    joint_alpha: float = param(0.6, "weight of the newest pose in the per-joint smoothing",
                               minimum=0.0, maximum=1.0, exclusive_minimum=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.gate_max_px < self.gate_px:
            raise ValueError(f"gate_max_px: {self.gate_max_px} is below gate_px {self.gate_px}")


@dataclass
class TemporalResult:
    """Clusters (members index the detections as given, ordered by first member), one track id
    per cluster (-1 = tentative track or temporal off), FLAG_* bits per cluster, stats."""

    clusters: list[Cluster]
    track_ids: np.ndarray
    flags: np.ndarray
    stats: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------
# track state
# ---------------------------------------------------------------------------------------
@dataclass
class Track:
    """One person followed through time. x (6,) root position (m) and velocity (m/s), Pc (6,6)
    its covariance; offsets (J,3) body joints minus root (m, NaN = never seen)."""

    key: int
    x: np.ndarray
    Pc: np.ndarray
    offsets: np.ndarray
    hits: int = 1
    misses: int = 0
    id: int = -1

    @property
    def joints(self) -> np.ndarray:
        """(J,3) predicted / current body joints, world m."""
        return self.x[:3] + self.offsets


def _root(joints: np.ndarray) -> np.ndarray:
    """(...,3) mean of the finite joints of (...,J,3); NaN if none."""
    ok = np.isfinite(joints).all(-1)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok[..., None], joints, 0.0).sum(-2) / n[..., None]


class Tracker3D:
    """Kalman root + smoothed offsets for a list of tracks; see the module docstring."""

    def __init__(self, params: TemporalParams):
        self.p = params
        self.tracks: list[Track] = []
        self._next_key = 0
        self._next_id = 0

    def reset(self) -> None:
        """End every track (the id counter keeps counting)."""
        self.tracks = []

    def predict(self, dt: float) -> None:
        """Move every track forward by dt seconds (constant velocity, white acceleration)."""
        if not self.tracks or dt <= 0:
            return
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        q = self.p.accel_std ** 2
        Q1 = q * np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]])
        Q = np.kron(Q1, np.eye(3))
        for t in self.tracks:  # one 6x6 product per person
            t.x = F @ t.x
            t.Pc = F @ t.Pc @ F.T + Q

    def start(self, joints: np.ndarray) -> Track:
        """A tentative track from a triangulated pose (J,3)."""
        root = _root(joints)
        Pc = np.diag([self.p.meas_std ** 2] * 3 + [4.0] * 3)  # velocity unknown: ~2 m/s std
        t = Track(self._next_key, np.concatenate([root, np.zeros(3)]), Pc, joints - root)
        self._next_key += 1
        self.tracks.append(t)
        self._confirm(t)
        return t

    def update(self, t: Track, joints: np.ndarray, meas_std: float | None = None) -> None:
        """Kalman update of the root with a pose (J,3) (NaN = unseen), smooth the offsets."""
        root = _root(joints)
        if np.isfinite(root).all():
            r = (meas_std or self.p.meas_std) ** 2
            S = t.Pc[:3, :3] + r * np.eye(3)
            K = t.Pc[:, :3] @ np.linalg.inv(S)
            t.x = t.x + K @ (root - t.x[:3])
            t.Pc = (np.eye(6) - K[:, :3] @ np.eye(3, 6)) @ t.Pc
            new = joints - root
            a = self.p.joint_alpha
            seen, known = np.isfinite(new).all(-1), np.isfinite(t.offsets).all(-1)
            blend = np.where((seen & known)[:, None], a * new + (1 - a) * t.offsets, t.offsets)
            t.offsets = np.where((seen & ~known)[:, None], new, blend)
        t.hits += 1
        t.misses = 0
        self._confirm(t)

    def _confirm(self, t: Track) -> None:
        if t.id < 0 and t.hits >= self.p.confirm_hits:
            t.id = self._next_id
            self._next_id += 1


# ---------------------------------------------------------------------------------------
# geometry helpers (batched)
# ---------------------------------------------------------------------------------------
def _project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project X (...,3) with P (...,3,4) broadcast: (uv (...,2) px, depth (...)); NaN behind."""
    h = np.einsum("...ij,...j->...i", P[..., :3], X) + P[..., 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = h[..., :2] / h[..., 2:3]
    return np.where((h[..., 2:3] > 0), uv, np.nan), h[..., 2]


def _depth(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(T,) median depth (m) of the points X (T,J,3) in the camera P (3,4); NaN if none in front."""
    _, z = _project(P, X)
    return _nanmedian(np.where(z > 0, z, np.nan))


def _nanmedian(a: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN; NaN where all are NaN. One sort (NaN sorts last)
    instead of np.nanmedian, whose generic path has a large fixed cost per call on small
    arrays."""
    srt = np.sort(a, axis=-1)
    n = np.isfinite(a).sum(-1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _triangulate_members(P: np.ndarray, uv: np.ndarray, present: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Joints X (T,J,3) from members padded to M views and each member's median reprojection
    error (T,M) px (inf where absent or not reprojectable).

    P (T,M,3,4), uv (T,M,J,2), present (T,M).
    """
    w = present.astype(np.float64)  # (T,M)
    Pj = np.broadcast_to(P[:, None], (P.shape[0], uv.shape[2]) + P.shape[1:])  # (T,J,M,3,4)
    X = dlt(Pj, uv.transpose(0, 2, 1, 3), np.broadcast_to(w[:, None], Pj.shape[:3]))
    proj, _ = _project(P[:, :, None], X[:, None])  # (T,M,J,2)
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(proj - uv, axis=-1)
    err = np.where(np.isfinite(err), err, np.nan)
    med = _nanmedian(err)
    return X, np.where(present & np.isfinite(med), med, np.inf)


def _verify(P: np.ndarray, uv: np.ndarray, present: np.ndarray, passes: np.ndarray,
            tau_px: float, min_support: float) -> tuple[np.ndarray, np.ndarray]:
    """Geometric verification of clusters padded to M members, as in the consistent clustering:
    every member must pass the pair gates with at least ``min_support`` of the other members
    (passes (T,M,M) bool) and reproject under tau_px (median over the body joints triangulated
    from all kept members). The worst member (least support, then largest error) is dropped
    until all pass or fewer than 2 remain. Returns (kept (T,M), joints (T,J,3) of the kept
    members, NaN where fewer than 2 are kept)."""
    keep = present.copy()
    for _ in range(max(present.shape[1] - 1, 1)):  # at most M-1 drops, batched over clusters
        X, err = _triangulate_members(P, uv, keep)
        others = np.maximum(keep.sum(1, keepdims=True) - 1, 1)
        support = (passes & keep[:, None, :]).sum(2) / others  # (T,M)
        bad = keep & ((err >= tau_px) | (support < min_support))
        todo = bad.any(1) & (keep.sum(1) >= 2)
        if not todo.any():
            break
        # least support first; the error (px, < 1e6) breaks ties
        badness = np.where(keep, (1.0 - support) * 1e6 + np.minimum(err, 1e6 - 1), -1.0)
        worst = np.argmax(badness, axis=1)
        keep[np.flatnonzero(todo), worst[todo]] = False
    X[keep.sum(1) < 2] = np.nan
    return keep, X


def _rays_nearest(cam_P: np.ndarray, center: np.ndarray, uv: np.ndarray, X_pred: np.ndarray
                  ) -> np.ndarray:
    """(J,3) points on the back-projected rays of uv (J,2) nearest to X_pred (J,3): one view
    plus the prediction (the view fixes the direction, the prediction the depth)."""
    M_inv = np.linalg.inv(cam_P[:, :3])
    d = (M_inv @ np.concatenate([uv, np.ones((len(uv), 1))], axis=1).T).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = np.einsum("jk,jk->j", X_pred - center, d)
    return center + s[:, None] * d


class _FrameView:
    """One frame set as the track stage reads it, built once per frame and shared by both
    assignment passes: every camera's detections padded to N rows (C = the rig's cameras;
    absent cameras and padding rows are NaN and invalid), the epipolar point rows of each
    camera (built on first use), and the pair-gate results already computed this frame."""

    def __init__(self, stage: "TemporalAssociator", by_cam: dict[int, FrameDetections],
                 body: np.ndarray):
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
            self.kp2[c, :fd.n] = fd.kpts2d[:, body]
            self.kp3[c, :fd.n] = fd.kpts3d[:, body]
            self.centers[c, :fd.n] = fd.centers
            ok = np.flatnonzero(fd.scores >= stage.params.tau_det)
            self.valid[c, ok] = True
            if ok.size:
                self.ok[c] = ok
        self._rows: dict[int, tuple[epipolar.PointRows, list[epipolar.PointRows | None]]] = {}
        self._known_keys = np.zeros(0, np.int64)  # sorted pair keys tested this frame
        self._known_ok = np.zeros(0, bool)

    def points(self, c: int) -> "tuple[epipolar.PointRows, list[epipolar.PointRows | None]]":
        """Camera c's points for the verification's epipolar gate and their screening subsets
        (association.screen_subsets, the decoder's copies where it made them; none for
        keypoints), converted once per frame."""
        if c not in self._rows:
            fd = self.by_cam[c]
            points = self.stage._gate_points(fd)
            whole = fd if points is fd.verts2d else None  # the decoder's copies describe it
            full = epipolar.point_rows(points, whole.block_ranges() if whole else None)
            mesh = self.stage.tp.verify_epipolar == "mesh"
            self._rows[c] = (full, screen_subsets(full, self.stage.params, whole) if mesh else [])
        return self._rows[c]

    def pair_ok(self, ca: np.ndarray, cb: np.ndarray, da: np.ndarray, db: np.ndarray
                ) -> np.ndarray:
        """(S,) bool pair gates of detection pairs, each distinct pair tested once per frame."""
        C = len(self.stage.rig)
        keys = ((ca * C + cb) * self.n + da) * self.n + db
        pos = np.minimum(np.searchsorted(self._known_keys, keys), max(self._known_keys.size - 1, 0))
        hit = self._known_keys.size > 0
        hit = hit & (self._known_keys[pos] == keys) if hit else np.zeros(keys.size, bool)
        ok = np.zeros(keys.size, bool)
        ok[hit] = self._known_ok[pos[hit]]
        new_keys, first = np.unique(keys[~hit], return_index=True)
        if new_keys.size:
            s = np.flatnonzero(~hit)[first]
            new_ok = self.stage._gate_pairs(self, ca[s], cb[s], da[s], db[s])
            ok[~hit] = new_ok[np.searchsorted(new_keys, keys[~hit])]
            keys_all = np.concatenate([self._known_keys, new_keys])
            order = np.argsort(keys_all, kind="stable")
            self._known_keys = keys_all[order]
            self._known_ok = np.concatenate([self._known_ok, new_ok])[order]
        return ok


# ---------------------------------------------------------------------------------------
# the stage
# ---------------------------------------------------------------------------------------
TEMPORAL_STAT_KEYS = ("tracks", "tracks_confirmed", "detections_explained", "detections_left",
                      "tracks_supported", "tracks_few_views", "tracks_one_view", "tracks_started",
                      "tracks_reacquired", "tracks_merged", "tracks_ended", "track_resets",
                      "verify_dropped", "t_track_ms", "t_associate_ms")


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
        self._F = rig.fundamental_matrices()
        self._pair_F = epipolar.pair_matrices(self._F)  # as the kernels take them, once
        self._centers = np.stack([c.center for c in rig.cameras])
        self._focal = np.array([0.5 * (c.K_rect[0, 0] + c.K_rect[1, 1]) for c in rig.cameras])
        self._last_stamp: int | None = None
        self.resets = 0

    def reset(self) -> None:
        """End every track; the next frame set starts from scratch."""
        self.tracker.reset()
        self._last_stamp = None

    def step(self, frames: Mapping[str, FrameDetections], stamp_ns: int) -> TemporalResult:
        """Associate one synchronised frame set (keyed by camera name) at stamp_ns (int ns)."""
        if not self.tp.temporal:
            res = associate(self.rig, frames, self.params)
            n = len(res.clusters)
            return TemporalResult(res.clusters, np.full(n, -1, np.int64), np.zeros(n, np.uint8),
                                  dict(res.stats))
        t0 = time.perf_counter()
        stats: dict[str, float] = dict.fromkeys(TEMPORAL_STAT_KEYS, 0.0)
        self._advance(int(stamp_ns), stats)
        names = [n for n in self.rig.names if n in frames]
        by_cam = {self.rig.index(n): frames[n] for n in names}
        J = next((fd.num_joints for fd in by_cam.values() if fd.n), 0)
        body = np.asarray(body_joints(J), np.int64) if J else np.zeros(0, np.int64)
        used = {c: np.zeros(fd.n, bool) for c, fd in by_cam.items()}
        out: dict[int, list] = {}  # track key -> [members (M,2), costs (M,), flags]
        if self.tracker.tracks and J:
            out = self._explain(by_cam, body, used, stats)
        stats["t_track_ms"] = (time.perf_counter() - t0) * 1e3

        t1 = time.perf_counter()
        # a camera none of whose detections a track explained goes in as given (no copy of its
        # vertex arrays); the others as the subset of what is left (few once tracks run)
        keep = {c: np.flatnonzero(~u) for c, u in used.items()}
        stats["detections_left"] = float(sum(
            int((by_cam[c].scores[k] >= self.params.tau_det).sum()) for c, k in keep.items()))
        res = associate(self.rig, {self.rig.names[c]: by_cam[c].select(k) if used[c].any()
                                   else by_cam[c] for c, k in keep.items()}, self.params)
        stats["t_associate_ms"] = (time.perf_counter() - t1) * 1e3
        for k, v in res.stats.items():
            stats.setdefault(k, v)
        new = [(np.stack([c.members[:, 0], keep_idx(keep, c.members)], axis=1), c.costs)
               for c in res.clusters]
        if new and J:
            self._attach(new, by_cam, body, out, stats)
        self._age(out, stats)
        return self._result(out, stats, t0)

    # -- steps ---------------------------------------------------------------------------
    def _advance(self, stamp_ns: int, stats: dict[str, float]) -> None:
        if self._last_stamp is not None:
            dt = (stamp_ns - self._last_stamp) * 1e-9
            if dt < 0 or dt > self.tp.max_gap_s:
                self.tracker.reset()
                self.resets += 1
                stats["track_resets"] = 1.0
            else:
                self.tracker.predict(dt)
        self._last_stamp = stamp_ns

    def _explain(self, by_cam: dict[int, FrameDetections], body: np.ndarray,
                 used: dict[int, np.ndarray], stats: dict[str, float]) -> dict[int, list]:
        """Steps 2-4: detections explained by the tracks' predictions, verified; then once more
        against the projections of each verified cluster's own triangulation (this frame's
        estimate, tighter than the prediction: a view where the prediction was ambiguous
        between two people is re-assigned by the views that agree)."""
        tracks = self.tracker.tracks
        view = _FrameView(self, by_cam, body)
        pred = np.stack([t.joints for t in tracks])  # (T,J,3)
        sig = np.sqrt(np.stack([t.Pc[0, 0] + t.Pc[1, 1] + t.Pc[2, 2] for t in tracks]) / 3.0)
        _, z = _project(self._P[:, None, None], pred[None])  # (C,T,J) m, all cameras at once
        depth = _nanmedian(np.where(z > 0, z, np.nan))  # (C,T)
        gate = np.minimum(self.tp.gate_px + self.tp.gate_sigma * self._focal[:, None] * sig
                          / depth, self.tp.gate_max_px).T  # (T,C) px
        cand = self._assign(view, pred, gate)
        cam, det, present, keep, X = self._verify_candidates(view, cand)
        refit = keep.sum(1) >= 2
        if refit.any() and self.tp.refine_px > 0:
            gate = np.where(refit[:, None], self.tp.refine_px, gate)
            again = self._assign(view, np.where(refit[:, None, None], X, pred), gate)
            if not np.array_equal(again, cand):  # the same candidates verify the same way
                cam, det, present, keep, X = self._verify_candidates(view, again)
        return self._take_explained(cam, det, present, keep, X,
                                    lambda c, d: view.kp2[c, d], used, stats)

    def _take_explained(self, cam: np.ndarray, det: np.ndarray, present: np.ndarray,
                        keep: np.ndarray, X: np.ndarray,
                        body_kpts: Callable[[int, int], np.ndarray], used: dict[int, np.ndarray],
                        stats: dict[str, float]) -> dict[int, list]:
        """Update every track from its verified members (padded (T,M) cam, det, present, keep;
        joints X (T,J,3)), or from one view and its prediction; mark the members used.
        body_kpts(c, d) -> (J,2) px body keypoints of detection d in camera c. Returns track key
        -> [members, costs, flags]."""
        tracks = self.tracker.tracks
        stats["verify_dropped"] = float((present & ~keep).sum())
        out: dict[int, list] = {}
        for i, t in enumerate(tracks):  # one iteration per person
            n = int(keep[i].sum())
            need = self.tp.min_track_views if t.id >= 0 else self.params.k_min
            if n >= max(need, 2):
                members = np.stack([cam[i, keep[i]], det[i, keep[i]]], axis=1)
                self.tracker.update(t, X[i])
                few = n < self.params.k_min
                stats["tracks_few_views"] += few
                out[t.key] = [members, np.full(n, np.nan),
                              FLAG_TRACKED | (FLAG_FEW_VIEWS if few else 0)]
            elif t.id >= 0 and present[i].any() and self.tp.one_view:
                c, d = self._one_view(present[i], keep[i], cam[i], det[i])
                self.tracker.update(t, _rays_nearest(self._P[c], self._centers[c],
                                                     body_kpts(c, d), t.joints),
                                    meas_std=self.tp.one_view_std)
                stats["tracks_one_view"] += 1
                out[t.key] = [np.array([[c, d]]), np.full(1, np.nan),
                              FLAG_TRACKED | FLAG_FEW_VIEWS | FLAG_ONE_VIEW]
            else:
                continue
            for c, d in out[t.key][0].tolist():
                used[c][d] = True
        stats["detections_explained"] = float(sum(u.sum() for u in used.values()))
        return out

    def _assign(self, view: "_FrameView", joints: np.ndarray, gate: np.ndarray) -> np.ndarray:
        """Per camera, Hungarian assignment of detections to the tracks' skeletons joints (T,J,3)
        on the median 2D body-keypoint distance (px) under gate (T,C) px. The distances of
        every track to every detection of every camera are one batched computation
        (detections padded per camera); only the assignment runs per camera. Returns the
        candidate detection (T,C) of each track in each camera (-1 = none)."""
        T, C = len(joints), len(self.rig)
        uv, _ = _project(self._P[:, None, None], joints[None])  # (C,T,J,2)
        diff = np.linalg.norm(uv[:, :, None] - view.kp2[:, None], axis=-1)  # (C,T,N,J)
        cost = _nanmedian(diff)  # (C,T,N)
        okc = view.valid[:, None] & np.isfinite(cost) & (cost < gate.T[:, :, None])
        if self.tp.pose_weight > 0:
            # the pose term only orders the candidates of a track or of a detection with more
            # than one gated partner in a camera: an isolated gated pair is assigned whatever
            # its cost (any other choice for its row or column is gated)
            contested = okc & ((okc.sum(2, keepdims=True) > 1) | (okc.sum(1, keepdims=True) > 1))
            cost = cost + self.tp.pose_weight * self._pose_cost(contested, joints, view.kp3,
                                                                 self.params.backend)
        cand = np.full((T, C), -1, np.int64)
        for c, ok in view.ok.items():  # one Hungarian per camera
            gated = okc[c][:, ok]
            rows, cols = linear_sum_assignment(np.where(gated, cost[c][:, ok], _GATED))
            real = gated[rows, cols]
            cand[rows[real], c] = ok[cols[real]]
        return cand

    def _verify_candidates(self, view: "_FrameView", cand: np.ndarray) -> tuple[np.ndarray, ...]:
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
        keep, X = _verify(self._P[cam], uv, present, passes, self.params.tau_verify,
                          self.params.min_support)
        return cam, det, present, keep, X

    @staticmethod
    def _pose_cost(okc: np.ndarray, joints: np.ndarray, kpts3d: np.ndarray,
                   backend: str = "auto") -> np.ndarray:
        """(C,T,N) PA-MPJPE (m) of each selected (okc) detection's 3D body pose (kpts3d (C,N,J,3))
        aligned onto the track's skeleton joints (T,J,3), one batched alignment over all
        cameras (procrustes backend); 0 where not selected or the track has unseen joints (no
        preference)."""
        out = np.zeros(okc.shape)
        c, t, n = np.nonzero(okc & np.isfinite(joints).all((1, 2))[None, :, None])
        if t.size:
            out[c, t, n] = np.nan_to_num(pa_mpjpe_finite(kpts3d[c, n], joints[t], backend))
        return out

    def _pair_gates(self, view: "_FrameView", cam: np.ndarray, det: np.ndarray,
                    present: np.ndarray) -> np.ndarray:
        """(T,M,M) bool: member pairs of each candidate cluster passing the association's pair
        gates (:meth:`_gate_pairs`); a pair already tested this frame (the refinement pass
        proposes mostly the same clusters) is looked up, not tested again."""
        T, M = present.shape
        a_idx, b_idx = np.triu_indices(M, 1)
        both = present[:, a_idx] & present[:, b_idx]  # members sorted by camera: ca < cb
        t, q = np.nonzero(both)
        ma, mb = a_idx[q], b_idx[q]
        ok = view.pair_ok(cam[t, ma], cam[t, mb], det[t, ma], det[t, mb])
        passes = np.zeros((T, M, M), bool)
        passes[t, ma, mb] = passes[t, mb, ma] = ok
        return passes

    def _gate_pairs(self, view: "_FrameView", ca: np.ndarray, cb: np.ndarray, da: np.ndarray,
                    db: np.ndarray) -> np.ndarray:
        """(S,) bool: detection pairs (camera ca < cb, detections da, db) passing the
        association's pair gates (bbox-centre reprojection, epipolar on mesh vertices or
        keypoints, PA-MPJPE cost of the lower camera's 3D pose aligned onto the other's under
        tau_cost), the same tests (core.geometry.multiview, core.association.gates.epipolar, core.geometry.procrustes) the cross-view
        association applies, on the few pairs inside the tracks' clusters only."""
        by_cam = view.by_cam
        ok = np.ones(ca.size, bool)
        p = self.params
        if p.reproj_gate and ca.size:
            uv = np.stack([view.centers[ca, da], view.centers[cb, db]], axis=1)  # (S,2,2)
            Ps = np.stack([self._P[ca], self._P[cb]], axis=1)
            ok &= reprojection_errors(Ps, uv, p.reproj_reduce) < p.tau_reproj_bbox
        if self.tp.verify_epipolar != "none" and ok.any():
            s = np.flatnonzero(ok)
            cams = sorted_unique(np.concatenate([ca[s], cb[s]])).tolist()
            rows = {c: view.points(c) for c in cams}
            # every camera pair in one kernel call per level; missing (NaN) points are not
            # counted
            ok[s] = epipolar.frame_screened_means(
                {c: full for c, (full, _) in rows.items()},
                screen_levels(rows, p), self._pair_F,
                ca[s], da[s], cb[s], db[s], p.tau_mesh,
                symmetric=p.epipolar_distance == "symmetric", early_exit=p.early_exit,
                backend=p.backend, precision=p.epipolar_precision)[0]
        if p.tau_cost > 0 and ok.any():
            s = np.flatnonzero(ok)
            J = next(fd.num_joints for fd in by_cam.values() if fd.n)
            joints = joint_subset(p.cost_joints, J)
            X = np.empty((s.size, joints.size, 3))
            Y = np.empty_like(X)
            for c, fd in by_cam.items():
                X[ca[s] == c] = fd.kpts3d[da[s][ca[s] == c]][:, joints]
                Y[cb[s] == c] = fd.kpts3d[db[s][cb[s] == c]][:, joints]
            ok[s] = pa_mpjpe_finite(X, Y, p.backend) < p.tau_cost  # NaN (too few joints) fails
        return ok

    def _gate_points(self, fd: FrameDetections) -> np.ndarray:
        """The (N,n,2) px the verification's epipolar gate compares (``verify_epipolar``):
        2D keypoints, or mesh vertices (the association's vertex subset)."""
        if self.tp.verify_epipolar == "sparse":
            return fd.kpts2d
        subset = epipolar.vertex_subset(fd.num_vertices, self.params.vertex_stride,
                                        self.params.vertex_count)
        return fd.verts2d if subset is None else fd.verts2d[:, subset]

    @staticmethod
    def _one_view(present: np.ndarray, keep: np.ndarray, cam: np.ndarray, det: np.ndarray
                  ) -> tuple[int, int]:
        """The single view left: the verified one if any, else the first candidate."""
        k = int(np.flatnonzero(keep if keep.any() else present)[0])
        return int(cam[k]), int(det[k])

    def _attach(self, new: list[tuple[np.ndarray, np.ndarray]],
                by_cam: dict[int, FrameDetections], body: np.ndarray,
                out: dict[int, list], stats: dict[str, float]) -> None:
        """Step 5: each new (members, costs) cluster merges into a track supported this frame,
        re-acquires an unsupported track, or starts a tentative one."""
        joints = self._triangulate([m for m, _ in new], by_cam, body)  # (K,J,3)
        tracks = self.tracker.tracks
        taken = np.zeros(len(new), bool)
        for group, merge in (([t for t in tracks if t.key in out], True),
                             ([t for t in tracks if t.key not in out], False)):
            if not group or taken.all():
                continue
            d = _mean_distance(np.stack([t.joints for t in group]), joints)  # (G,K)
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
                    old = out[t.key]
                    if np.intersect1d(old[0][:, 0], members[:, 0]).size:
                        if old[2] & FLAG_ONE_VIEW:  # the cross-view cluster beats one view
                            self.tracker.update(t, joints[k])
                            out[t.key] = [members, costs, 0]
                        continue  # else the same person twice in a camera: the track's wins
                    both = np.concatenate([old[0], members])
                    order = np.argsort(both[:, 0], kind="stable")
                    few = FLAG_FEW_VIEWS if len(both) < self.params.k_min else 0
                    out[t.key] = [both[order], np.full(len(both), np.nan),
                                  (old[2] & ~FLAG_FEW_VIEWS & ~FLAG_ONE_VIEW) | few]
                else:
                    self.tracker.update(t, joints[k])
                    out[t.key] = [members, costs, 0]
                    stats["tracks_reacquired"] += 1
        for k in np.flatnonzero(~taken):
            t = self.tracker.start(joints[k])
            out[t.key] = [new[k][0], new[k][1], 0]
            stats["tracks_started"] += 1

    def _triangulate(self, clusters: list[np.ndarray], by_cam: dict[int, FrameDetections],
                     body: np.ndarray) -> np.ndarray:
        """(K,J,3) DLT body joints of clusters (no member dropped; associate verified them)."""
        K, M = len(clusters), max(len(m) for m in clusters)
        cam = np.zeros((K, M), np.int64)
        present = np.zeros((K, M), bool)
        uv = np.full((K, M, body.size, 2), np.nan)
        for k, m in enumerate(clusters):  # one row per person
            cam[k, :len(m)] = m[:, 0]
            present[k, :len(m)] = True
            for j, (c, d) in enumerate(m.tolist()):
                uv[k, j] = by_cam[c].kpts2d[d][body]
        X, _ = _triangulate_members(self._P[cam], uv, present)
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

    def _result(self, out: dict[int, list], stats: dict[str, float], t0: float
                ) -> TemporalResult:
        """Clusters of >= 2 views (one view triangulates nothing), ordered by first member."""
        ids = {t.key: t.id for t in self.tracker.tracks}
        rows = sorted(((m, c, key, f) for key, (m, c, f) in out.items() if len(m) >= 2),
                      key=lambda r: tuple(r[0][0].tolist()))
        clusters = [Cluster(members=m, costs=c) for m, c, _, _ in rows]
        track_ids = np.array([ids.get(key, -1) for _, _, key, _ in rows], np.int64)
        flags = np.array([f for _, _, _, f in rows], np.uint8)
        stats["clusters"] = float(len(clusters))
        stats["t_total_ms"] = (time.perf_counter() - t0) * 1e3
        return TemporalResult(clusters, track_ids, flags, stats)


def keep_idx(keep: dict[int, np.ndarray], members: np.ndarray) -> np.ndarray:
    """Map members' detection indices in the per-camera subsets back to the indices as given."""
    return np.array([keep[int(c)][int(d)] for c, d in members.tolist()], np.int64)


def _mean_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(G,K) mean distance (m) over joints finite in both of A (G,J,3) and B (K,J,3)."""
    both = np.isfinite(A).all(-1)[:, None] & np.isfinite(B).all(-1)[None]
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(A[:, None] - B[None], axis=-1)
    n = both.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(both, d, 0.0).sum(-1) / n, np.inf)
