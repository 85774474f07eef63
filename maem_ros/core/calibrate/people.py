"""People mode: calibrate a rig (extrinsics, floor, scale, time offsets) from the players.

Stages (each its own module): pairwise relative poses from the skeletons (correspondence) ->
initial rig (initial_rig) -> per-frame cross-view people (matching) -> tracks (tracks) ->
bundle adjustment (bundle) -> people matched again under the refined rig and adjusted again ->
time offsets (timing), observations moved to the reference times, adjusted again -> world frame
(world; court points: court) -> per-camera statistics and warnings.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry.camera import Rig
from .bundle import DEFAULT_SCHEDULE, WARM_SCHEDULE, BundleOptions, BundleProblem, BundleResult, bundle_adjust
from .correspondence import MIN_SUPPORT, PairEstimate, estimate_pair, hypothesis_frames
from .court import CourtPoints, court_similarity
from .initial_rig import InitialRig, initial_rig
from .matching import match_frames
from .people_data import PeopleData
from .timing_joint import TIME_METHODS, TIME_TESTS, estimate_offsets
from .tracks import Tracks, link_tracks, projection_matrices, shift_in_time, triangulate
from .world import Similarity, floor_frame, skeleton_scale, stature


@dataclass
class PeopleOptions:
    """hypothesis_frames: frames the pair search uses at least; hypothesis_pairs: more frames
    are used while a camera pair's detection pairs stay under this (few people give few
    agreeing pairs per frame: two people need ~100 frames where twenty need 15);
    first_pass_frames: frames the first bundle adjustment (from the rough start) uses;
    gates_px: epipolar gates (px) of the first and second matching; extra_match_rounds: up to
    this many more matchings at the last gate while a camera's rotation still changes by more
    than settled_deg (deg) per round; max_offset_s: largest time offset searched (s);
    time_method: "gauss_seidel" (one camera at a time, to convergence) or "joint" (two
    Gauss-Seidel rounds, then all offsets refined together; less accurate on the bench's
    humanm3_4 scene so far, see doc/calibration.md) or "gauss_seidel_partial" (the default
    before: also where the tracks have gaps, which biases the offsets; timing.kernel_tracks);
    time_test: the joint significance test, "kernel" (the other cameras' tracks smoothed by
    the estimator's Gaussian at each camera's capture times) or "interpolated" (the former:
    moved by linear interpolation, which zeroed true offsets under half a frame)."""

    hypothesis_frames: int = 15
    hypothesis_pairs: int = 2000
    extra_match_rounds: int = 3
    settled_deg: float = 0.02
    first_pass_frames: int = 20
    gates_px: tuple[float, float] = (40.0, 12.0)
    refine_intrinsics: bool = False
    estimate_time: bool = True
    max_offset_s: float = 0.15
    time_method: str = "gauss_seidel"
    time_test: str = "kernel"
    time_rounds: int = 4
    person_height: float | None = None
    court: CourtPoints | None = None
    seed: int = 0


@dataclass
class CameraReport:
    """One camera's result: observations used, reprojection error median / p90 (px), 1-sigma
    rotation (deg) and centre (m) uncertainty, time offset (s) and its standard error (s; NaN
    when not estimated or with two cameras); calibrated False when the camera could not be
    connected to the rest."""

    name: str
    calibrated: bool
    observations: int = 0
    median_px: float = np.nan
    p90_px: float = np.nan
    rotation_sd_deg: float = np.nan
    centre_sd_m: float = np.nan
    time_offset_s: float = 0.0
    time_offset_sd_s: float = np.nan


@dataclass
class PeopleCalibration:
    """The calibrated rig (world frame, m, time offsets), per-camera reports, warnings, the
    people's 3D tracks (T,F,J,3) world m, the pairwise estimates and stage run times (s)."""

    rig: Rig
    cameras: list[CameraReport]
    warnings: list[str]
    points: np.ndarray
    pairs: list[PairEstimate]
    scale_source: str
    timings: dict = field(default_factory=dict)
    tracks: Tracks | None = None


def _pairs_and_start(data: PeopleData, opts: PeopleOptions) -> tuple[list[PairEstimate], InitialRig]:
    """Steps a and b: every camera pair's relative pose from the people (consensus over
    detection pairs) and the initial rig over the camera graph; ValueError when fewer than two
    cameras connect or the options name an unknown time method or test."""
    if opts.time_method not in TIME_METHODS:
        raise ValueError(
            f"people calibration: PeopleOptions.time_method {opts.time_method!r} is not one of {TIME_METHODS}"
        )
    if opts.time_test not in TIME_TESTS:
        raise ValueError(
            f"people calibration: PeopleOptions.time_test {opts.time_test!r} is not one of {TIME_TESTS}"
        )
    rng = np.random.default_rng(opts.seed)
    C = data.num_cameras
    frames = hypothesis_frames(data, _pair_search_frames(data, opts))
    pairs = [
        p
        for a in range(C)
        for b in range(a + 1, C)
        if (p := estimate_pair(data, a, b, frames, rng)) is not None
    ]
    start = initial_rig(C, pairs)
    if start.connected.sum() < 2:
        raise ValueError(
            "people calibration: no two cameras share enough people "
            f"(each pair needs {MIN_SUPPORT} agreeing detection pairs)"
        )
    return pairs, start


def calibrate_people(data: PeopleData, opts: PeopleOptions | None = None) -> PeopleCalibration:
    """Run every stage on ``data``; ValueError when fewer than two cameras can be connected."""
    opts = opts or PeopleOptions()
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    C = data.num_cameras
    pairs, start = _pairs_and_start(data, opts)
    timings["pairs"] = time.perf_counter() - clock
    warnings = _pair_warnings(data, pairs, start)
    R, t = start.R, start.t
    K = np.stack([c.K_rect for c in data.rig])
    result: BundleResult | None = None
    tracks, prob = None, None
    # the last gate is repeated while the rig still moves: in a crowd the first matches under
    # a rough rig hold wrong pairs that pull it, and each rematch removes some (humanm3_4,
    # 20 players: 2.9 deg off after one 12 px pass, 0.07 deg after three)
    gates = list(opts.gates_px) + [opts.gates_px[-1]] * opts.extra_match_rounds
    R_before = R
    for k, gate in enumerate(gates):
        if k >= len(opts.gates_px) and _rig_change_deg(R_before, R) < opts.settled_deg:
            break
        R_before = R
        clock = time.perf_counter()
        tracks = link_tracks(data, match_frames(data, R, t, gate), projection_matrices(K, R, t))
        warm = result is not None
        # the rough start's long robust schedule on a subset of the frames (the rig is fixed
        # by far fewer points than a game holds); the warm pass on all of them
        subset = None if warm else hypothesis_frames(data, opts.first_pass_frames)
        result, prob = _adjust(tracks, K, R, t, opts, start.connected, warm, subset)
        R, t = result.R, result.t
        timings[f"match+bundle {gate:g}px"] = (
            timings.get(f"match+bundle {gate:g}px", 0.0) + time.perf_counter() - clock
        )
    if result is None or tracks is None or prob is None:
        raise ValueError("people calibration: PeopleOptions.gates_px is empty (no matching pass)")
    delta, delta_sd = np.zeros(C), np.full(C, np.nan)
    if opts.estimate_time and data.num_frames >= 3:
        clock = time.perf_counter()
        ok = np.flatnonzero(start.connected)
        observed = tracks
        # a rig adjusted on unsynchronised observations absorbs part of an offset (a camera
        # turned along the people's main motion): estimate, adjust on the moved observations,
        # estimate again from that rig, until the offsets settle
        for rnd in range(opts.time_rounds):
            P = projection_matrices(K, R, t)
            before = delta.copy()
            # later rounds only refine: the rig moved a little, the offsets a fraction of a frame
            delta[ok], delta_sd[ok] = estimate_offsets(
                P[ok],
                observed.U[ok],
                opts.max_offset_s * data.fps,
                opts.time_method,
                start=delta[ok] if rnd else None,
                test=opts.time_test,
            )
            if np.all(np.abs(delta) <= 0.02) or np.all(np.abs(delta - before) <= 0.03):
                break
            tracks = Tracks(np.stack([shift_in_time(observed.U[c], delta[c]) for c in range(C)]), observed.D)
            result, prob = _adjust(tracks, K, R, t, opts, start.connected, True, None)
            R, t = result.R, result.t
        timings["time offsets"] = time.perf_counter() - clock
    clock = time.perf_counter()
    X = result.points.reshape(tracks.U.shape[1:4] + (3,))
    sim, scale_source = _world(data, X, tracks.D, R, t, start.connected, opts, warnings)
    timings["world frame"] = time.perf_counter() - clock
    rig = _output_rig(data, R, t, sim, result, delta, start.connected)
    cams = _camera_reports(data, prob, result, sim, delta, delta_sd, start.connected)
    warnings += _camera_warnings(cams)
    return PeopleCalibration(
        rig=rig,
        cameras=cams,
        warnings=warnings,
        points=sim.apply(X),
        pairs=pairs,
        scale_source=scale_source,
        timings=timings,
        tracks=tracks,
    )


def _rig_change_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Largest rotation (deg) between the cameras' orientations of two rigs (C,3,3)."""
    c = (np.einsum("cij,cij->c", Ra, Rb) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))).max())


def _pair_search_frames(data: PeopleData, opts: PeopleOptions) -> int:
    """Frames for the pair search: opts.hypothesis_frames, or more while a camera pair's
    detection pairs (frames x people seen by one camera x by the other) stay under
    opts.hypothesis_pairs (its cost grows with them, its evidence too)."""
    per_frame = np.array([c.scores.size for c in data.cameras], float) / max(data.num_frames, 1)
    pairs_per_frame = max(float(np.median(per_frame)) ** 2, 1.0)
    return max(opts.hypothesis_frames, int(opts.hypothesis_pairs / pairs_per_frame))


def _adjust(
    tracks: Tracks, K, R, t, opts: PeopleOptions, connected: np.ndarray, warm: bool, frames: np.ndarray | None
):
    """Bundle-adjust the tracks' observations (every (track, frame, joint) a free point)
    from the rig (R, t), only ``frames`` when given; the observations of each detection form
    one outlier group."""
    C, T, F, J = tracks.shape
    U = tracks.U.copy()
    U[~connected] = np.nan
    if frames is not None:
        U[:, :, np.setdiff1d(np.arange(F), frames)] = np.nan
    seen = np.all(np.isfinite(U), axis=-1)
    c, tr, f, j = np.nonzero(seen)
    X0 = triangulate(projection_matrices(K[connected], R[connected], t[connected]), U[connected])
    X0 = np.nan_to_num(X0.reshape(-1, 3))
    Rs = np.where(connected[:, None, None], R, np.eye(3))
    ts = np.where(connected[:, None], t, 0.0)
    group = c * (int(tracks.D.max(initial=0)) + 2) + tracks.D[c, tr, f]
    prob = BundleProblem(
        K=K,
        R=Rs,
        t=ts,
        points=X0,
        obs_camera=c,
        obs_point=(tr * F + f) * J + j,
        obs_uv=U[c, tr, f, j],
        obs_group=group,
    )
    fixed = (int(np.flatnonzero(connected)[0]),) + tuple(np.flatnonzero(~connected))
    opts_b = BundleOptions(
        schedule=WARM_SCHEDULE if warm else DEFAULT_SCHEDULE,
        refine_focal=opts.refine_intrinsics,
        refine_k1=opts.refine_intrinsics,
        fixed_cameras=fixed,
        covariance=True,
    )
    return bundle_adjust(prob, opts_b), prob


def _world(data: PeopleData, X, rows, R, t, connected, opts: PeopleOptions, warnings):
    """The similarity to the world frame and where its scale came from."""
    first = -R[connected][0].T @ t[connected][0]
    sim = floor_frame(X, data.feet, data.head, first)
    if opts.person_height is not None:
        h = stature(X, data.names)
        if not np.isfinite(h):
            raise ValueError(
                "person height: the detections lack the ankle, knee, hip, shoulder "
                "and nose joints it is measured with"
            )
        s, source = opts.person_height / h, f"person height {opts.person_height:g} m"
    else:
        s = skeleton_scale(X, rows, [c.kpts3d for c in data.cameras], data.names)
        source = "metric skeletons"
        if not np.isfinite(s):
            s, source = 1.0, "none (arbitrary units)"
            warnings.append("scale: no bone lengths to measure; the rig's scale is arbitrary")
    sim = sim.then(Similarity(float(s), np.eye(3), np.zeros(3)))
    if opts.court is not None:
        cams = []
        for c, cam in enumerate(data.rig):
            if connected[c]:
                Rw, tw = sim.camera(R[c], t[c])
                cams.append(replace(cam, R=Rw, t=tw))
        sim = sim.then(court_similarity(opts.court, Rig(cams)))
        source = "court points"
    return sim, source


def _output_rig(data: PeopleData, R, t, sim: Similarity, result: BundleResult, delta, connected) -> Rig:
    cams = []
    for c, cam in enumerate(data.rig):
        if not connected[c]:
            continue
        Rw, tw = sim.camera(R[c], t[c])
        f = result.focal_scale[c]
        K, K_rect = cam.K.copy(), cam.K_rect.copy()
        K[:2, :2] *= f
        K_rect[:2, :2] *= f
        D = cam.D.copy()
        if result.k1[c] and not cam.is_fisheye:
            D[0] += result.k1[c]
        cams.append(replace(cam, R=Rw, t=tw, K=K, K_rect=K_rect, D=D, time_offset=float(delta[c] / data.fps)))
    return Rig(cams)


def _camera_reports(
    data: PeopleData, prob: BundleProblem, result: BundleResult, sim: Similarity, delta, delta_sd, connected
) -> list[CameraReport]:
    err = result.errors()
    out = []
    for c, cam in enumerate(data.rig):
        if not connected[c]:
            out.append(CameraReport(cam.name, False))
            continue
        e = err[(prob.obs_camera == c) & result.inliers]
        e = e[np.isfinite(e)]
        cov = result.camera_cov[c] if result.camera_cov is not None else np.full((6, 6), np.nan)
        out.append(
            CameraReport(
                cam.name,
                True,
                int(e.size),
                float(np.median(e)) if e.size else np.nan,
                float(np.percentile(e, 90)) if e.size else np.nan,
                float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))),
                float(sim.s * np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))),
                float(delta[c] / data.fps),
                float(delta_sd[c] / data.fps),
            )
        )
    return out


def _pair_warnings(data: PeopleData, pairs: list[PairEstimate], start: InitialRig) -> list[str]:
    names = data.rig.names
    out = [
        f"camera pair {names[a]}-{names[b]}: too little shared evidence ({s} agreeing "
        f"detection pairs, need {MIN_SUPPORT}); not used for the initial rig"
        for a, b, s in start.weak_pairs
    ]
    out += [
        f"camera pair {names[a]}-{names[b]}: its own relative pose disagrees with the rig by {d:.1f} deg"
        for a, b, d in start.disagreeing
    ]
    out += [
        f"camera {names[c]}: NOT CALIBRATED (shares too few people with the other cameras)"
        for c in np.flatnonzero(~start.connected)
    ]
    return out


def _camera_warnings(cams: list[CameraReport]) -> list[str]:
    done = [c for c in cams if c.calibrated]
    if not done:
        return []
    med_obs = np.median([c.observations for c in done])
    med_err = np.median([c.median_px for c in done])
    out = []
    for c in done:
        if c.observations < 0.25 * med_obs:
            out.append(f"camera {c.name}: weak: {c.observations} observations (median camera {med_obs:.0f})")
        if c.median_px > 3 * med_err:
            out.append(
                f"camera {c.name}: weak: median reprojection error {c.median_px:.1f} px "
                f"(median camera {med_err:.1f} px)"
            )
        if c.rotation_sd_deg > 0.5:
            out.append(f"camera {c.name}: weak: rotation uncertainty {c.rotation_sd_deg:.2f} deg")
    return out
