"""Approximate-time synchroniser for per-camera messages (pure logic, injectable clock).

message_filters is not available from PyPI, so this is the project's own. Every call
passes ``now_ns`` (the caller's clock: wall or sim time), which keeps it testable.

Rules (doc/design.md §5):

- Each camera has a short queue, kept sorted by stamp (at most ``queue_size``
  messages; when full the oldest is dropped, reason ``queue_full``).
- The reference is the oldest queued message. A camera is *present* when its
  oldest queued message lies within ``[ref, ref + slop]``. A camera is not waited for when
  its oldest message is newer than ``ref + slop`` (stamps per camera only increase), when it
  is *dead* (missing from the last ``dead_after_sets`` sets with nothing queued since), or
  when it is *lagging* (below).
- A FrameSet is emitted, stamped with the reference stamp, as soon as no camera is waited
  for, or once ``max_wait`` has passed since the reference message arrived; if fewer than
  ``min_cameras`` are present then, only the reference message is dropped
  (``too_few_cameras``). Emitted sets never go back in time: a message whose stamp is not
  newer than the last emitted reference is dropped (``late``, or ``lagging`` for a camera
  known to lag).
- Lag: each camera's transport latency (arrival - stamp, which includes any clock offset) is
  compared with the median latency of the other cameras. A camera whose relative lag exceeds
  ``max_wait`` on two messages in a row is *lagging*: sets stop waiting for it (the sets
  before that wait ``max_wait`` at most), so it cannot hold the others back; it rejoins as
  soon as one of its messages arrives with a lag under half the window (hysteresis: a lag
  fluctuating around the window does not flap) or in time for its set. With ``max_lag_ns`` > 0 a
  camera lagging by at most ``max_lag`` is compensated instead: sets wait up to its lag plus
  ``max_wait`` for it (whole graph delayed by that lag, the camera kept).
- Stamp jumps: a camera's stamp that steps back by more than ``slop`` or lies more than
  ``jump_ns`` ahead of the other cameras (by arrival time) is held aside for that camera, not
  queued. If the camera goes on as before, the held messages are dropped (``stale`` /
  ``future``) and nothing else happens. If most live cameras jump (bag loop, restart of the
  whole stream), the synchroniser resets: queued messages are dropped (``reset``), the reset
  is counted once (``stats.resets``) and the held messages are replayed on the new timeline.
  A step back within ``slop`` or a repeated stamp is dropped (``out_of_order``).
- Time offsets: a camera's message stamp + its rig ``time_offset`` (Camera.time_offset, s) is
  its true capture time. :func:`capture_stamp_ns` is the one place that adds it: the
  synchroniser (``time_offsets``) queues, compares and emits capture times, and the offline
  pipeline matches frames by them (:func:`match_capture_times`).
"""

from __future__ import annotations

import statistics
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, overload

import numpy as np

#: consecutive late samples that make a camera lagging (one sample under the window rejoins it)
LAG_SAMPLES = 2


@overload
def capture_stamp_ns(stamp_ns: int, time_offset_s: float) -> int: ...


@overload
def capture_stamp_ns(stamp_ns: np.ndarray, time_offset_s: float) -> np.ndarray: ...


def capture_stamp_ns(stamp_ns: int | np.ndarray, time_offset_s: float) -> int | np.ndarray:
    """A camera's true capture time (ns): its message stamp (ns) + its rig time_offset (s); an
    int for an int stamp, an int64 array for an array of stamps."""
    offset_ns = int(round(float(time_offset_s) * 1e9))
    if isinstance(stamp_ns, np.ndarray):
        return stamp_ns.astype(np.int64) + offset_ns
    return int(stamp_ns) + offset_ns


def match_capture_times(
    reference_ns: Sequence[int], stamps_ns: Sequence[int], time_offset_s: float, tolerance_ns: int
) -> np.ndarray:
    """Offline frame matching: for each reference time (ns), the index into ``stamps_ns`` (one
    camera's message stamps, ns, sorted) whose capture time (stamp + ``time_offset_s``) is
    nearest, or -1 when none lies within ``tolerance_ns``."""
    ref = np.asarray(reference_ns, dtype=np.int64)
    cap = capture_stamp_ns(np.asarray(stamps_ns, dtype=np.int64), time_offset_s)
    if cap.size == 0:
        return np.full(ref.shape, -1, dtype=np.int64)
    right = np.clip(np.searchsorted(cap, ref), 0, cap.size - 1)
    left = np.clip(right - 1, 0, cap.size - 1)
    nearest = np.where(np.abs(cap[left] - ref) <= np.abs(cap[right] - ref), left, right)
    return np.where(np.abs(cap[nearest] - ref) <= int(tolerance_ns), nearest, -1)


@dataclass
class FrameSet:
    """Messages of one instant: items by camera name, missing cameras in rig order;
    ``stamp_ns`` is the reference message's capture time (stamp + its camera's time offset);
    ``ready_ns``: when the set could first go out (its last message arrived, or its wait for a
    missing camera ran out; never before the set ahead of it), on the caller's clock: how long
    it then waits for the caller is the caller's backlog (core.backlog)."""

    stamp_ns: int
    items: dict[str, Any]
    missing: list[str] = field(default_factory=list)
    ready_ns: int = 0


class SyncDrop(str, Enum):
    """Why the synchroniser dropped a message (the /diagnostics reason is ``sync_<value>``)."""

    LATE = "late"  # older than the last emitted set
    LAGGING = "lagging"  # late, from a camera known to lag by more than the window
    TOO_FEW_CAMERAS = "too_few_cameras"  # reference of a set with fewer than min_cameras
    OUT_OF_ORDER = "out_of_order"  # repeated stamp or a step back within slop
    STALE = "stale"  # far step back of one camera (the others went on)
    FUTURE = "future"  # far ahead of the other cameras (the others went on)
    QUEUE_FULL = "queue_full"  # oldest queued message pushed out
    RESET = "reset"  # queued when the whole stream jumped and the sync reset


@dataclass
class SyncStats:
    """Cumulative counts: every message received ends up in a set, queued, held or ``dropped``."""

    received: int = 0
    sets: int = 0
    partial_sets: int = 0
    timeouts: int = 0  # sets emitted only because max_wait ran out on an awaited camera
    resets: int = 0
    dropped: Counter = field(default_factory=Counter)  # SyncDrop -> messages

    @property
    def total_dropped(self) -> int:
        return sum(self.dropped.values())


@dataclass
class SyncEvent:
    """A state change worth one log line: ``kind`` lagging | rejoined | reset."""

    kind: str
    camera: str | None
    text: str


@dataclass
class _Msg:
    stamp_ns: int
    arrival_ns: int
    item: Any


class ApproximateTimeSync:
    """Group per-camera messages whose capture times lie within ``slop_ns`` of a reference.

    ``time_offsets``: camera -> s added to its stamps (the rig's time_offset; absent = 0).
    """

    def __init__(
        self,
        cameras: Sequence[str],
        slop_ns: int,
        max_wait_ns: int,
        min_cameras: int = 2,
        queue_size: int = 16,
        dead_after_sets: int = 3,
        max_lag_ns: int = 0,
        jump_ns: int = 1_000_000_000,
        time_offsets: Mapping[str, float] | None = None,
    ):
        cameras = list(cameras)
        offsets = dict(time_offsets or {})
        unknown = sorted(set(offsets) - set(cameras))
        if unknown:
            raise ValueError(f"time_offsets: unknown camera(s) {unknown}; expected some of {cameras}")
        if not all(np.isfinite(float(v)) for v in offsets.values()):
            raise ValueError(f"time_offsets: must be finite seconds, got {offsets}")
        self.time_offsets = {c: float(offsets.get(c, 0.0)) for c in cameras}
        if not cameras or len(set(cameras)) != len(cameras):
            raise ValueError(f"cameras: need a non-empty list of distinct names, got {cameras}")
        for name, value in (("slop_ns", slop_ns), ("max_wait_ns", max_wait_ns), ("max_lag_ns", max_lag_ns)):
            if int(value) < 0:
                raise ValueError(f"{name}: must be >= 0, got {value}")
        if not 1 <= int(min_cameras) <= len(cameras):
            raise ValueError(f"min_cameras: must be in 1..{len(cameras)}, got {min_cameras}")
        if int(queue_size) < 1:
            raise ValueError(f"queue_size: must be >= 1, got {queue_size}")
        if int(dead_after_sets) < 1:
            raise ValueError(f"dead_after_sets: must be >= 1, got {dead_after_sets}")
        if int(jump_ns) <= int(slop_ns):
            raise ValueError(f"jump_ns: must be > slop_ns ({slop_ns}), got {jump_ns}")
        self.cameras = cameras
        self.slop_ns = int(slop_ns)
        self.max_wait_ns = int(max_wait_ns)
        self.max_lag_ns = int(max_lag_ns)
        self.jump_ns = int(jump_ns)
        self.min_cameras = int(min_cameras)
        self.queue_size = int(queue_size)
        self.dead_after_sets = int(dead_after_sets)
        self.stats = SyncStats()
        self._events: list[SyncEvent] = []
        self._queues: dict[str, deque[_Msg]] = {c: deque() for c in cameras}
        self._held: dict[str, deque[tuple[SyncDrop, _Msg]]] = {c: deque() for c in cameras}
        self._clear()

    # -- state ----------------------------------------------------------------------------
    def _clear(self) -> None:
        for q in self._queues.values():
            q.clear()
        for h in self._held.values():
            h.clear()
        self._last_stamp: dict[str, int] = {}
        self._missed: dict[str, int] = {}  # sets missed in a row with nothing queued since
        self._latency: dict[str, int] = {}  # last arrival - stamp per camera, ns
        self._lag: dict[str, deque[int]] = {}  # last lags relative to the other cameras, ns
        self._lagging: set[str] = set()  # not waited for until their lag falls back
        self._last_emitted: int | None = None
        self._last_ready = 0  # ready_ns of the last emitted set

    def reset(self) -> None:
        """Drop every queued and held message (counted ``reset``) and forget all stamps."""
        lost = self.pending() + sum(len(h) for h in self._held.values())
        self._drop(SyncDrop.RESET, lost)
        self.stats.resets += 1
        self._clear()

    def pending(self) -> int:
        """Messages currently queued (held jump candidates not included)."""
        return sum(len(q) for q in self._queues.values())

    def lagging(self) -> dict[str, float]:
        """Cameras currently lagging beyond the window: relative lag in seconds."""
        return {c: self._lag_ns(c) / 1e9 for c in self.cameras if self._is_lagging(c)}

    def take_events(self) -> list[SyncEvent]:
        """State changes since the last call (for one log line each)."""
        events, self._events = self._events, []
        return events

    @property
    def counters(self) -> dict[str, int]:
        """Flat view of :attr:`stats` (``dropped_<reason>`` keys) for reports and tests."""
        out = {
            "received": self.stats.received,
            "sets": self.stats.sets,
            "partial_sets": self.stats.partial_sets,
            "timeouts": self.stats.timeouts,
            "resets": self.stats.resets,
        }
        out.update({f"dropped_{r.value}": self.stats.dropped[r] for r in SyncDrop})
        return out

    def _drop(self, reason: SyncDrop, n: int = 1) -> None:
        if n:
            self.stats.dropped[reason] += n

    # -- input ----------------------------------------------------------------------------
    def add(
        self,
        camera: str,
        stamp_ns: int,
        item: Any,
        now_ns: int,
        arrival_ns: int | None = None,
        poll: bool = True,
    ) -> list[FrameSet]:
        """Queue one message and return the frame sets that became complete.

        ``stamp_ns``: the message's stamp; the camera's time offset is added here.

        ``arrival_ns`` (same clock as ``now_ns``, at most ``now_ns``): when the message reached
        this process, if it waited before the caller took it (a busy node: the transport's
        receive time); the ``max_wait`` deadline and the lag are measured from it. Default
        ``now_ns``. ``poll=False`` only queues (the caller takes every other pending message
        first and then calls :meth:`poll` once, so no set is declared partial while a message
        of it is already waiting to be taken); sets a stream reset replays are still returned.
        """
        if camera not in self._queues:
            raise ValueError(f"camera: unknown camera {camera!r}; expected one of {self.cameras}")
        now_ns = int(now_ns)
        arrival_ns = now_ns if arrival_ns is None else min(int(arrival_ns), now_ns)
        self.stats.received += 1
        stamp_ns = capture_stamp_ns(stamp_ns, self.time_offsets[camera])
        out = self._accept(camera, _Msg(stamp_ns, arrival_ns, item))
        return out + self.poll(now_ns) if poll else out

    def _baseline(self, camera: str) -> int | None:
        """Median latency of the other cameras that are alive (None without any)."""
        others = [v for c, v in self._latency.items() if c != camera and not self._dead(c)]
        return int(statistics.median_low(others)) if others else None

    def _accept(self, camera: str, m: _Msg) -> list[FrameSet]:
        prev = self._last_stamp.get(camera)
        base = self._baseline(camera)
        latency = m.arrival_ns - m.stamp_ns
        if prev is not None and m.stamp_ns <= prev:
            if prev - m.stamp_ns <= self.slop_ns:
                self._drop(SyncDrop.OUT_OF_ORDER)
                return []
            if not self._outlier_before(camera, latency, base):
                return self._hold(camera, SyncDrop.STALE, m)
            self._drop_queued_from(camera, m.stamp_ns)
        elif base is not None and latency < base - self.jump_ns:
            return self._hold(camera, SyncDrop.FUTURE, m)
        self._release_held(camera)
        forward = prev is None or m.stamp_ns > prev
        self._last_stamp[camera] = m.stamp_ns
        self._latency[camera] = latency
        if forward and base is not None:
            self._update_lag(camera, latency - base)
        lagging = self._is_lagging(camera)
        if not lagging:  # a camera that merely lags within the window is kept alive
            self._missed[camera] = 0
        if self._last_emitted is not None and m.stamp_ns <= self._last_emitted:
            self._drop(SyncDrop.LAGGING if lagging else SyncDrop.LATE)
            return []
        self._missed[camera] = 0
        if lagging:  # in time for its set although not waited for: back in the window
            self._rejoin(camera, "a message in time")
        q = self._queues[camera]
        if len(q) >= self.queue_size:
            q.popleft()
            self._drop(SyncDrop.QUEUE_FULL)
        q.append(m)
        return []

    def _outlier_before(self, camera: str, latency: int, base: int | None) -> bool:
        """The others agree with this stamp but not with the camera's previous one (accepted
        before there was anyone to compare with): re-anchor the camera instead of holding."""
        prev = self._latency.get(camera)
        return (
            base is not None
            and prev is not None
            and abs(latency - base) <= self.jump_ns
            and abs(prev - base) > self.jump_ns
        )

    def _drop_queued_from(self, camera: str, stamp_ns: int) -> None:
        """Remove ``camera``'s queued messages at or after ``stamp_ns`` (counted ``future``)."""
        q = self._queues[camera]
        while q and q[-1].stamp_ns >= stamp_ns:
            q.pop()
            self._drop(SyncDrop.FUTURE)

    def _update_lag(self, camera: str, lag: int) -> None:
        """Enter lagging after LAG_SAMPLES lags beyond the window; leave it (hysteresis, so a
        noisy lag around the window does not flap) at a lag under half the window."""
        self._lag.setdefault(camera, deque(maxlen=LAG_SAMPLES)).append(lag)
        if (
            camera not in self._lagging
            and self._lag_ns(camera) > self.max_wait_ns
            and not self._compensated(camera)
        ):
            self._lagging.add(camera)
            self._events.append(
                SyncEvent(
                    "lagging",
                    camera,
                    f"camera {camera} lags the others by {lag / 1e6:.0f} ms (> window): not waited for",
                )
            )
        elif camera in self._lagging and (lag <= self.max_wait_ns // 2 or self._compensated(camera)):
            self._rejoin(camera, f"lag {lag / 1e6:.0f} ms")

    def _rejoin(self, camera: str, why: str) -> None:
        self._lagging.discard(camera)
        self._events.append(
            SyncEvent("rejoined", camera, f"camera {camera} back within the window ({why}): waited for again")
        )

    def _hold(self, camera: str, reason: SyncDrop, m: _Msg) -> list[FrameSet]:
        """Keep a jumped message aside; reset and replay when most live cameras jumped."""
        held = self._held[camera]
        if len(held) >= self.queue_size:
            self._drop(held.popleft()[0])
        held.append((reason, m))
        live = [c for c in self.cameras if c in self._last_stamp and not self._dead(c)]
        jumped = [c for c in live if self._held[c]]
        if len(jumped) < max(1, len(live) // 2 + 1):
            return []
        replay = sorted(
            ((msg.arrival_ns, k, c, msg) for c in self.cameras for k, (_, msg) in enumerate(self._held[c])),
            key=lambda e: e[:2],
        )
        for c in self.cameras:
            self._held[c].clear()
        kind = "back" if reason is SyncDrop.STALE else "forward"
        self.reset()
        self._events.append(
            SyncEvent(
                "reset",
                None,
                f"{len(jumped)} of {len(live)} cameras "
                f"jumped {kind} (bag loop or restart): synchroniser reset",
            )
        )
        out: list[FrameSet] = []
        for _, _, c, msg in replay:
            out += self._accept(c, msg)
        return out

    def _release_held(self, camera: str) -> None:
        """The camera went on as before: its held jump candidates were outliers."""
        for reason, _ in self._held[camera]:
            self._drop(reason)
        self._held[camera].clear()

    # -- output ---------------------------------------------------------------------------
    def _lag_ns(self, camera: str) -> int:
        """The camera's lag behind the others: the smallest of its last LAG_SAMPLES (0 until
        that many were measured), so one delayed message does not make a camera lag."""
        lags = self._lag.get(camera)
        return min(lags) if lags is not None and len(lags) == LAG_SAMPLES else 0

    def _compensated(self, camera: str) -> bool:
        return bool(self.max_lag_ns) and self._lag_ns(camera) <= self.max_lag_ns

    def _is_lagging(self, camera: str) -> bool:
        return camera in self._lagging

    def _wait_ns(self, camera: str) -> int:
        """How long after the reference's arrival a set waits for ``camera``."""
        lag = self._lag_ns(camera)
        if self.max_lag_ns and self.max_wait_ns < lag <= self.max_lag_ns:
            return lag + self.max_wait_ns
        return self.max_wait_ns

    def _dead(self, camera: str) -> bool:
        return self._missed.get(camera, 0) >= self.dead_after_sets

    def poll(self, now_ns: int, complete_only: bool = False) -> list[FrameSet]:
        """Emit every frame set that is complete or has waited long enough at ``now_ns``.

        ``complete_only``: emit only sets that wait for no camera (every camera is present,
        dead, lagging, or already past the set's stamp), never one that timed out: for a
        caller still taking messages that may hold the awaited ones."""
        now_ns = int(now_ns)
        out: list[FrameSet] = []
        while True:
            heads = {c: q[0] for c, q in self._queues.items() if q}
            if not heads:
                return out
            ref_cam = min(heads, key=lambda c: heads[c].stamp_ns)
            ref = heads[ref_cam]
            limit = ref.stamp_ns + self.slop_ns
            present = [c for c in self.cameras if c in heads and heads[c].stamp_ns <= limit]
            awaited = [
                c for c in self.cameras if c not in heads and not self._dead(c) and not self._is_lagging(c)
            ]
            if awaited and (
                complete_only or now_ns - ref.arrival_ns < max(self._wait_ns(c) for c in awaited)
            ):
                return out
            if len(present) < self.min_cameras:
                self._queues[ref_cam].popleft()
                self._drop(SyncDrop.TOO_FEW_CAMERAS)
                continue
            self.stats.timeouts += bool(awaited)
            ready = max(heads[c].arrival_ns for c in present)
            if awaited:
                ready = max(ready, ref.arrival_ns + max(self._wait_ns(c) for c in awaited))
            out.append(self._emit(ref.stamp_ns, present, min(now_ns, ready)))

    def _emit(self, stamp_ns: int, present: list[str], ready_ns: int) -> FrameSet:
        items = {c: self._queues[c].popleft().item for c in present}
        missing = [c for c in self.cameras if c not in items]
        for c in missing:
            self._missed[c] = self._missed.get(c, 0) + 1
        self._last_emitted = stamp_ns
        self.stats.sets += 1
        if missing:
            self.stats.partial_sets += 1
        self._last_ready = max(self._last_ready, ready_ns)
        return FrameSet(stamp_ns, items, missing, self._last_ready)


@dataclass
class GuardResult:
    """What :meth:`StampGuard.push` decided: items to process now (in order), items dropped
    with their reason (``stale_stamp`` / ``future_stamp`` / ``duplicate_stamp``), and whether
    the stream jumped back (confirmed: state keyed on time, such as a tracker, must reset)."""

    accepted: list[tuple[int, Any]] = field(default_factory=list)
    dropped: list[tuple[str, Any]] = field(default_factory=list)
    jumped_back: bool = False


class StampGuard:
    """Monotonic stamps for one stream, with jumps confirmed by the messages after them.

    A repeated stamp is dropped. A step back, or a step forward by more than the time that
    passed since the previous message (``now_ns``, the caller's clock) plus ``jump_ns``, is
    held: if the next ``confirm`` messages continue from it (each newer than the previous, by
    no more than the same bound) the stream jumped (bag loop, restart, seek) and the held
    messages are released in order; if a message continues the old timeline instead, the held
    ones were outliers (stamp 0, an old duplicate, a far-future stamp) and are dropped. A
    hostile stamp thus costs no valid frame, and a real jump costs ``confirm`` messages of
    delay, no loss. A slow stream (frame period above ``jump_ns``) is no jump: the bound grows
    with the time between its messages.
    """

    def __init__(self, jump_ns: int = 1_000_000_000, confirm: int = 2):
        if int(jump_ns) <= 0 or int(confirm) < 1:
            raise ValueError(f"jump_ns > 0 and confirm >= 1 required, got {jump_ns}, {confirm}")
        self.jump_ns, self.confirm = int(jump_ns), int(confirm)
        self.last: int | None = None
        self._last_arrival = 0
        self._held: list[tuple[int, int, Any]] = []  # (stamp, arrival, item)

    def _follows(self, stamp_ns: int, prev: int, prev_arrival: int, now_ns: int) -> bool:
        return prev < stamp_ns <= prev + self.jump_ns + max(0, now_ns - prev_arrival)

    def push(self, stamp_ns: int, item: Any, now_ns: int = 0) -> GuardResult:
        """Decide about one message arriving at ``now_ns`` (ns, any clock; 0 = stamps only)."""
        stamp_ns, now_ns, out = int(stamp_ns), int(now_ns), GuardResult()
        last = self.last
        if last is None:
            self._accept(stamp_ns, now_ns)
            out.accepted.append((stamp_ns, item))
            return out
        if self._held and self._follows(stamp_ns, self._held[-1][0], self._held[-1][1], now_ns):
            self._held.append((stamp_ns, now_ns, item))
            if len(self._held) > self.confirm:
                out.jumped_back = self._held[0][0] < last
                out.accepted = [(st, it) for st, _, it in self._held]
                self._held = []
                self._accept(stamp_ns, now_ns)
            return out
        if stamp_ns == last:
            out.dropped.append(("duplicate_stamp", item))
        elif self._follows(stamp_ns, last, self._last_arrival, now_ns):
            self._accept(stamp_ns, now_ns)
            out.accepted.append((stamp_ns, item))
        else:  # a jump: held until the next messages confirm or refute it
            self._drop_held(out)
            self._held = [(stamp_ns, now_ns, item)]
            return out
        self._drop_held(out)
        return out

    def _accept(self, stamp_ns: int, now_ns: int) -> None:
        self.last, self._last_arrival = stamp_ns, now_ns

    def _drop_held(self, out: GuardResult) -> None:
        for stamp, _, item in self._held:
            out.dropped.append(("stale_stamp" if stamp < (self.last or 0) else "future_stamp", item))
        self._held = []

    def reset(self) -> None:
        self.last, self._held = None, []
