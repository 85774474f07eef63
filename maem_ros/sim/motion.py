"""Player and bystander motion on the court (world: origin at the centre, z up, metres).

A steering simulation at the scene fps, vectorised over persons (one Python step per frame):
each player seeks a target with an arrival slow-down (running, then stopping), limited
acceleration and turn rate, and separation from the others. Plays alternate between the two
baskets; within each play a rebound event sends 5-7 players under the basket (crowding, arms
up); between events players re-target (cuts, jogs, stops). Referees/bystanders walk along the
sidelines following the play. One second of warm-up is simulated and dropped so frame 0 is
already in motion. Deterministic per seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rigs import BASKETS, COURT_LENGTH, COURT_WIDTH

ACCEL_MAX = 7.0  # m/s^2
TURN_RATE = 7.0  # rad/s
SEPARATION = 0.9  # m, players closer than this push apart


@dataclass
class Motion:
    """Per-frame state, arrays (F,P): pos (F,P,2) m, speed m/s, heading rad, phase rad,
    crouch 0..1, arm_raise 0..1, head_yaw rad; height (P,) m, width (P,) scale, team (P,) int
    (0/1 players, 2 bystanders)."""

    pos: np.ndarray
    speed: np.ndarray
    heading: np.ndarray
    phase: np.ndarray
    crouch: np.ndarray
    arm_raise: np.ndarray
    head_yaw: np.ndarray
    height: np.ndarray
    width: np.ndarray
    team: np.ndarray


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def simulate_motion(
    num_frames: int, fps: float, players: int, bystanders: int, seed: int, lead: int = 0
) -> Motion:
    """Simulate ``players`` + ``bystanders`` persons for ``num_frames`` frames at ``fps``.

    ``lead``: also keep that many warm-up frames before frame 0 (at the start of the arrays;
    at most the one second of warm-up): the motion a camera whose capture runs early sees.
    Frames 0.. are the same whatever ``lead`` and however many frames follow.
    """
    if num_frames < 1 or fps <= 0 or players < 0 or bystanders < 0 or players + bystanders < 1:
        raise ValueError(
            f"motion: need frames >= 1, fps > 0 and at least one person "
            f"(frames={num_frames}, fps={fps}, players={players}, bystanders={bystanders})"
        )
    if not 0 <= lead <= int(round(fps)):
        raise ValueError(f"motion: lead {lead} outside 0..{int(round(fps))} (one second of warm-up)")
    rng = np.random.default_rng([int(seed), 7001])
    crowd = _Crowd.start(rng, players, bystanders)
    dt = 1.0 / fps
    warm = int(round(fps)) - lead  # simulated steps before the first kept frame
    play = _Play.start(rng, first_kept_s=(warm + lead) * dt)
    record = _Record(num_frames + lead, len(crowd.height))
    for step in range(warm + num_frames + lead):
        t = step * dt
        play.direct(rng, crowd, t)
        crowd.move(play, t, dt)
        if step >= warm:
            record.keep(step - warm, crowd, t)
    return record.motion(crowd)


@dataclass
class _Crowd:
    """Every person's fixed traits (P,) and moving state, world metres / seconds / radians."""

    is_player: np.ndarray  # (P,) bool: players first, then bystanders (referees)
    team: np.ndarray  # (P,) 0/1 players, 2 bystanders
    height: np.ndarray  # (P,) m
    width: np.ndarray  # (P,) body width scale
    vmax: np.ndarray  # (P,) m/s
    side_y: np.ndarray  # (P,) m, the sideline a bystander walks along
    pos: np.ndarray  # (P,2) m
    vel: np.ndarray  # (P,2) m/s
    heading: np.ndarray  # (P,) rad
    phase: np.ndarray  # (P,) gait phase, rad
    crouch: np.ndarray  # (P,) 0..1
    arm: np.ndarray  # (P,) arm raise 0..1
    target: np.ndarray  # (P,2) m, where each person heads
    retarget_at: np.ndarray  # (P,) s
    hold_until: np.ndarray  # (P,) s, a stopped player stands still until then
    raise_until: np.ndarray  # (P,) s, arms up until then (rebounds)
    yaw_freq: np.ndarray  # (P,) Hz of the head's look-around
    yaw_phase: np.ndarray  # (P,) rad

    @classmethod
    def start(cls, rng: np.random.Generator, players: int, bystanders: int) -> _Crowd:
        """Traits and start positions (players on court, bystanders beside a sideline)."""
        P = players + bystanders
        is_player = np.arange(P) < players
        team = np.where(is_player, np.arange(P) % 2, 2)
        height = np.where(is_player, rng.uniform(1.78, 2.08, P), rng.uniform(1.62, 1.86, P))
        width = np.where(is_player, rng.uniform(0.9, 1.15, P), rng.uniform(0.92, 1.12, P))
        vmax = np.where(is_player, rng.uniform(5.0, 7.0, P), rng.uniform(2.5, 3.5, P))
        hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
        side_y = np.where(np.arange(P) % 2 == 0, -1.0, 1.0) * (hy + rng.uniform(0.8, 1.5, P))
        pos = np.stack([rng.uniform(-hx + 2, hx - 2, P), rng.uniform(-hy + 1.5, hy - 1.5, P)], axis=1)
        pos[~is_player, 1] = side_y[~is_player]
        pos[~is_player, 0] = rng.uniform(-8, 8, (~is_player).sum())
        heading = rng.uniform(-np.pi, np.pi, P)
        phase = rng.uniform(0, 2 * np.pi, P)
        retarget_at = rng.uniform(0.0, 0.6, P)
        yaw_freq, yaw_phase = rng.uniform(0.2, 0.6, P), rng.uniform(0, 2 * np.pi, P)
        return cls(
            is_player=is_player,
            team=team,
            height=height,
            width=width,
            vmax=vmax,
            side_y=side_y,
            pos=pos,
            vel=np.zeros((P, 2)),
            heading=heading,
            phase=phase,
            crouch=np.zeros(P),
            arm=np.zeros(P),
            target=pos.copy(),
            retarget_at=retarget_at,
            hold_until=np.zeros(P),
            raise_until=np.zeros(P),
            yaw_freq=yaw_freq,
            yaw_phase=yaw_phase,
        )

    def move(self, play: _Play, t: float, dt: float) -> None:
        """One step of ``dt`` s: steering, contacts, heading, gait phase, crouch and arms."""
        hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
        is_player = self.is_player
        self.vel = _steer(self.pos, self.vel, self.target, self.vmax, dt)
        pos = _resolve_contacts(self.pos + self.vel * dt)
        pos[is_player] = np.clip(pos[is_player], [-hx - 0.8, -hy - 0.8], [hx + 0.8, hy + 0.8])
        self.pos = pos
        speed = np.linalg.norm(self.vel, axis=1)
        basket = BASKETS[0 if play.side < 0 else 1, :2]
        look = np.where(is_player[:, None], basket - pos, np.stack([play.mean_x - pos[:, 0], -pos[:, 1]], 1))
        want = np.where(
            speed > 1.0, np.arctan2(self.vel[:, 1], self.vel[:, 0]), np.arctan2(look[:, 1], look[:, 0])
        )
        self.heading = _wrap(
            self.heading + np.clip(_wrap(want - self.heading), -TURN_RATE * dt, TURN_RATE * dt)
        )
        cadence = np.where(speed > 0.2, 0.85 + 0.12 * speed, 0.0)  # strides per second
        self.phase = (self.phase + 2 * np.pi * cadence * dt) % (2 * np.pi)
        k = 1.0 - np.exp(-dt / 0.25)
        self.crouch += k * (np.where(is_player & (speed < 1.5), 0.35, 0.0) - self.crouch)
        self.arm += k * ((t < self.raise_until).astype(float) - self.arm)


@dataclass
class _Play:
    """The game around the players: which basket is attacked, when the play turns over and
    when its rebound comes (s)."""

    side: int  # +1: attacking the +x basket
    end: float
    rebound_at: float
    mean_x: float = 0.0  # m, the players' mean x this step (the referees follow it)

    @classmethod
    def start(cls, rng: np.random.Generator, first_kept_s: float) -> _Play:
        side = int(rng.integers(0, 2)) * 2 - 1
        end = rng.uniform(3.0, 4.5)
        # the first rebound soon after the first kept frame: crowding shows even in 3 s scenes
        return cls(side=side, end=end, rebound_at=first_kept_s + rng.uniform(0.5, 1.3))

    def direct(self, rng: np.random.Generator, crowd: _Crowd, t: float) -> None:
        """Turnovers, rebounds and new targets at time ``t`` s."""
        if t >= self.end:  # transition: attack the other basket
            self.side = -self.side
            self.end = t + rng.uniform(4.0, 6.5)
            self.rebound_at = t + rng.uniform(2.0, 3.5)
            crowd.retarget_at[:] = t
        if t >= self.rebound_at:
            self._rebound(rng, crowd, t)
        due = (t >= crowd.retarget_at) & (t >= crowd.hold_until)
        if due.any():
            _retarget(
                rng,
                due,
                crowd.is_player,
                crowd.pos,
                crowd.target,
                self.side,
                crowd.hold_until,
                crowd.retarget_at,
                t,
                crowd.side_y,
            )
        # follow the play with the referees
        hx = COURT_LENGTH / 2
        is_player = crowd.is_player
        self.mean_x = crowd.pos[is_player, 0].mean() if is_player.any() else 0.0
        ref = ~is_player
        crowd.target[ref, 0] = np.clip(
            self.mean_x + np.where(np.arange(len(is_player))[ref] % 2 == 0, -3.0, 3.0), -hx + 1, hx - 1
        )
        crowd.target[ref, 1] = crowd.side_y[ref]

    def _rebound(self, rng: np.random.Generator, crowd: _Crowd, t: float) -> None:
        """5-7 players nearest the attacked basket crowd under it with their arms up."""
        basket = BASKETS[0 if self.side < 0 else 1, :2]
        cand = np.flatnonzero(crowd.is_player)
        n = min(len(cand), int(rng.integers(5, 8)))
        near = cand[np.argsort(np.linalg.norm(crowd.pos[cand] - basket, axis=1))[:n]]
        ang = rng.uniform(-np.pi / 2, np.pi / 2, n) + (np.pi if self.side > 0 else 0.0)
        rad = rng.uniform(0.6, 2.3, n)
        crowd.target[near] = basket + np.stack([np.cos(ang), np.sin(ang)], 1) * rad[:, None]
        crowd.retarget_at[near] = t + rng.uniform(1.6, 2.4, n)
        crowd.raise_until[near] = t + rng.uniform(1.2, 1.8, n)
        self.rebound_at = np.inf


class _Record:
    """The kept frames' state, (F,P) arrays."""

    def __init__(self, frames: int, persons: int) -> None:
        self.pos = np.zeros((frames, persons, 2))
        self.arrays = {
            k: np.zeros((frames, persons)) for k in ("speed", "heading", "phase", "crouch", "arm", "yaw")
        }

    def keep(self, f: int, crowd: _Crowd, t: float) -> None:
        out = self.arrays
        self.pos[f] = crowd.pos
        out["speed"][f] = np.linalg.norm(crowd.vel, axis=1)
        out["heading"][f], out["phase"][f] = crowd.heading, crowd.phase
        out["crouch"][f], out["arm"][f] = crowd.crouch, crowd.arm
        out["yaw"][f] = 0.45 * np.sin(2 * np.pi * crowd.yaw_freq * t + crowd.yaw_phase)

    def motion(self, crowd: _Crowd) -> Motion:
        out = self.arrays
        return Motion(
            pos=self.pos,
            speed=out["speed"],
            heading=out["heading"],
            phase=out["phase"],
            crouch=out["crouch"],
            arm_raise=out["arm"],
            head_yaw=out["yaw"],
            height=crowd.height,
            width=crowd.width,
            team=crowd.team,
        )


def _retarget(rng, due, is_player, pos, target, play_side, hold_until, retarget_at, t, side_y) -> None:
    hx, hy = COURT_LENGTH / 2, COURT_WIDTH / 2
    idx = np.flatnonzero(due & is_player)
    n = len(idx)
    if n:
        kind = rng.choice(3, size=n, p=[0.55, 0.25, 0.2])  # cut/run, short jog, stop
        x = play_side * rng.uniform(1.0, hx - 0.5, n)
        y = rng.uniform(-hy + 0.7, hy - 0.7, n)
        jog = pos[idx] + rng.normal(0.0, 2.0, (n, 2))
        new = np.where((kind == 0)[:, None], np.stack([x, y], 1), jog)
        new = np.where((kind == 2)[:, None], pos[idx], new)
        target[idx] = np.clip(new, [-hx + 0.3, -hy + 0.3], [hx - 0.3, hy - 0.3])
        hold_until[idx] = t + np.where(kind == 2, rng.uniform(0.4, 1.2, n), 0.0)
        retarget_at[idx] = t + rng.uniform(0.7, 1.8, n)
    retarget_at[due & ~is_player] = t + 1.0


def _steer(pos, vel, target, vmax, dt) -> np.ndarray:
    d = target - pos
    dist = np.linalg.norm(d, axis=1, keepdims=True)
    want_speed = np.minimum(vmax[:, None], 1.6 * dist)  # arrival: decelerate near the target
    desired = np.where(dist > 1e-6, d / np.maximum(dist, 1e-6) * want_speed, 0.0)
    for ahead, gain in ((0.0, 25.0), (0.4, 12.0)):  # now, and where everyone will be: players dodge
        p = pos + ahead * vel
        diff = p[:, None, :] - p[None, :, :]
        gap = np.linalg.norm(diff, axis=2) + np.eye(len(pos)) * 1e3
        push = np.where(
            (gap < SEPARATION)[..., None], diff / gap[..., None] * (SEPARATION - gap)[..., None], 0.0
        )
        desired = desired + gain * push.sum(axis=1)
    dv = desired - vel
    n = np.linalg.norm(dv, axis=1, keepdims=True)
    dv = dv * np.minimum(1.0, ACCEL_MAX * dt / np.maximum(n, 1e-9))
    return vel + dv


def _resolve_contacts(pos: np.ndarray, min_gap: float = 0.5, iterations: int = 3) -> np.ndarray:
    """Push apart persons closer than ``min_gap`` m (bodies never interpenetrate)."""
    for _ in range(iterations):
        diff = pos[:, None, :] - pos[None, :, :]
        gap = np.linalg.norm(diff, axis=2) + np.eye(len(pos)) * 1e3
        deficit = np.clip(min_gap - gap, 0.0, None)
        if not deficit.any():
            break
        unit = diff / np.maximum(gap, 1e-6)[..., None]
        pos = pos + 0.5 * (unit * deficit[..., None]).sum(axis=1)
    return pos


#: amplitude (rad) of the slow per-person pose variation added to each gait angle: people hold
#: their arms, torso and head differently, so poses differ between persons (as in real games)
STYLE_AMPLITUDE = {
    "sh_flex_l": 0.45,
    "sh_flex_r": 0.45,
    "sh_abd_l": 0.3,
    "sh_abd_r": 0.3,
    "elbow_l": 0.5,
    "elbow_r": 0.5,
    "wrist_l": 0.3,
    "wrist_r": 0.3,
    "hip_flex_l": 0.15,
    "hip_flex_r": 0.15,
    "hip_abd_l": 0.08,
    "hip_abd_r": 0.08,
    "knee_l": 0.2,
    "knee_r": 0.2,
    "twist": 0.3,
    "lean": 0.1,
    "side_lean": 0.07,
    "head_pitch": 0.2,
    "finger_curl": 0.25,
}
#: lower bounds that keep joints anatomically plausible after the variation
ANGLE_FLOOR = {
    "elbow_l": 0.03,
    "elbow_r": 0.03,
    "knee_l": 0.03,
    "knee_r": 0.03,
    "sh_abd_l": 0.04,
    "sh_abd_r": 0.04,
    "hip_abd_l": 0.0,
    "hip_abd_r": 0.0,
    "finger_curl": 0.05,
}


def pose_style(
    num_frames: int, fps: float, persons: int, seed: int, first_frame: int = 0
) -> dict[str, np.ndarray]:
    """Smooth per-person angle offsets (F,P) rad: two random sinusoids (0.1-0.6 Hz) per angle,
    for frames ``first_frame`` .. ``first_frame + num_frames - 1`` (negative: before frame 0)."""
    rng = np.random.default_rng([int(seed), 7002])
    t = (np.arange(num_frames) + first_frame)[:, None, None] / fps  # (F,1,1)
    out = {}
    for key, amp in STYLE_AMPLITUDE.items():
        freq = rng.uniform(0.1, 0.6, (1, persons, 2))
        phase = rng.uniform(0, 2 * np.pi, (1, persons, 2))
        weight = rng.uniform(0.3, 1.0, (1, persons, 2))
        out[key] = amp * (weight * np.sin(2 * np.pi * freq * t + phase)).sum(-1) / 1.3
    return out
