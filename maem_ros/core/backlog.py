"""A live node's overload policy: work never goes through stale frames (pure logic).

A node that got less CPU than it needs for a while (a busy neighbour, garbage collection, a
burst) finds several frames waiting for it at once. Working through all of them in order keeps
it behind for good at the input rate: its latency stays at the length of the hiccup. This
policy skips the stale ones instead, counted by the caller (``dropped/behind``):

- Each frame (an association frame set, a clusters message) has a *ready* time: when the node
  could first have processed it (the frame set's last message arrived, or its ``max_wait`` ran
  out; a message's receive time, or earlier when it queued on the way: ros/intake.py), on the
  caller's clock (ns).
- Its *backlog* is how long it has waited for the node since: ``now - ready``.
- When a frame waiting exceeds the *bound*, the node is behind and catches up at once: every
  frame but the newest is skipped (``catch_up: newest``, default; the freshest frame the node
  has is always worth processing). ``catch_up: stale`` skips only the frames beyond the bound
  and works through the rest in order. A backlog within the bound (a short hiccup) is worked
  through either way, without a loss.
- Why newest by default: with ``stale`` a node whose throughput is a little below the input
  rate settles at the bound, working through frames one bound old for good (measured at
  60 fps: latency stuck near 150 ms in both nodes); with ``newest`` each catch-up brings its
  latency back to one frame's work (doc/performance_live.md has the figures).
- The bound is ``max_backlog`` seconds, or with ``max_backlog`` 0 (default) BACKLOG_PERIODS
  frame periods (the median interval of the last stamps seen), at least MIN_BACKLOG_S, so it
  follows the camera rate: 67 ms at 60 fps, 133 ms at 30 fps.
- ``keep_every_set``: nothing is skipped (bag replays that want every frame: maem-demo,
  maem-play faster than real time); the backlog is still measured and reported.

The node is *behind* while it skips frames or works on frames older than the bound; the
episode ends at the first decision whose oldest frame waited at most half the bound
(hysteresis). :meth:`Backlog.status` says whether it is behind now, since when, and how long
the episodes were (/diagnostics).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from maem_ros.core.paramspec import Params, param

#: frame periods of backlog a live node tolerates before it skips frames (automatic bound):
#: a hiccup of a few frames (a collection, a scheduling gap) is absorbed without a loss, a
#: longer one costs frames instead of latency
BACKLOG_PERIODS = 4.0
#: the automatic bound's floor (s): a node this short of time is jitter, not behind
MIN_BACKLOG_S = 0.05
#: frame periods a frame may wait for the node before it is *late*: the next frame is due and the
#: node is falling behind (the association node then runs its light step: core/tracking/temporal.py)
LATE_PERIODS = 1.0
#: s of wall time a node's load (the share of it its callbacks took: :class:`LoadMeter`) is
#: measured over: a quarter second, 15 frames at 60 fps, follows a change of the input within
#: a few frames and averages a single slow frame out
LOAD_WINDOW_S = 0.25
#: stamp intervals the frame period is the median of
PERIOD_SAMPLES = 31
#: an episode with no decision for this many bounds (at least 1 s) ended with its last one
#: (the input stopped while the node was behind)
IDLE_BOUNDS = 4

T = TypeVar("T")


@dataclass
class BacklogParams(Params):
    """How a live node bounds the frames waiting for it (module docstring); one definition
    for every node that has the policy."""

    max_backlog: float = param(
        0.0,
        "s, a frame that waited longer than this for the node (it "
        "fell behind) is skipped unless it is the newest, counted "
        f"dropped/behind; 0 = automatic: {BACKLOG_PERIODS:g} frame "
        f"periods (median stamp interval), at least "
        f"{MIN_BACKLOG_S:g} s",
        minimum=0.0,
    )
    catch_up: str = param(
        "newest",
        "what a node that fell behind (a frame waited beyond the "
        "bound) skips: 'newest' = every waiting frame but the "
        "newest, 'stale' = only the frames beyond the bound "
        "(works through the rest in order)",
        choices=("newest", "stale"),
    )
    keep_every_set: bool = param(
        False,
        "process every frame however far behind (bag replays "
        "that want every frame: maem-demo, maem-play faster "
        "than real time); default: a live node skips stale "
        "frames",
    )


@dataclass
class BacklogStatus:
    """What /diagnostics shows (times in s, on the caller's clock)."""

    bound_s: float  # the current bound (nan: keep_every_set)
    behind: bool  # in an episode now
    behind_for_s: float  # how long the current episode has lasted (0 when not behind)
    episodes: int  # episodes ended
    behind_total_s: float  # time behind, ended episodes plus the current one
    longest_s: float  # longest episode, the current one included
    last_backlog_s: float  # the oldest frame's backlog at the last decision
    max_backlog_s: float  # the largest such backlog since the previous status (0: none)
    skipped: int  # frames skipped since the start


class Backlog(Generic[T]):
    """The overload policy of one node (module docstring); ``now_ns``/``ready_ns`` are the
    caller's clock (ns), the same for both."""

    def __init__(self, params: BacklogParams):
        self.params = params
        self._stamps: deque[int] = deque(maxlen=PERIOD_SAMPLES + 1)
        self._episode_start: int | None = None
        self._last_decision: int | None = None
        self._episodes = 0
        self._total_ns = 0
        self._longest_ns = 0
        self._last_backlog_ns = 0
        self._max_backlog_ns = 0
        self.skipped = 0

    # -- the bound ------------------------------------------------------------------------
    def observe(self, stamp_ns: int) -> None:
        """A frame's stamp (skipped or not): the frame period is measured from them."""
        stamp_ns = int(stamp_ns)
        if self._stamps and stamp_ns <= self._stamps[-1]:
            if stamp_ns < self._stamps[-1]:  # the stream went back (a loop): measure anew
                self._stamps.clear()
            else:
                return
        self._stamps.append(stamp_ns)

    def period_ns(self) -> int | None:
        """Median interval of the last stamps (None before two were seen)."""
        if len(self._stamps) < 2:
            return None
        return int(np.median(np.diff(np.fromiter(self._stamps, np.int64))))

    def bound_ns(self) -> int | None:
        """Backlog beyond which frames are skipped (None: keep_every_set)."""
        if self.params.keep_every_set:
            return None
        if self.params.max_backlog > 0:
            return int(round(self.params.max_backlog * 1e9))
        return self._auto_bound()

    # -- decisions ------------------------------------------------------------------------
    def select(self, frames: Sequence[T], ready_ns: Sequence[int], now_ns: int) -> tuple[list[T], list[T]]:
        """(kept, skipped) of ``frames`` waiting together, in the given (stamp) order: when
        one's backlog ``now_ns - ready_ns`` exceeds the bound, every one but the last (newest)
        is skipped (``catch_up: stale``: only those beyond the bound); the newest never.
        Records the decision for :meth:`status`."""
        frames, now_ns = list(frames), int(now_ns)
        if not frames:
            return [], []
        waited = [max(0, now_ns - int(r)) for r in ready_ns]
        bound = self.bound_ns()
        if bound is None:
            stale = [False] * len(frames)
        else:
            stale = [w > bound for w in waited[:-1]] + [False]
            if self.params.catch_up == "newest" and any(stale):
                stale = [True] * (len(frames) - 1) + [False]
        kept = [f for f, s in zip(frames, stale) if not s]
        skipped = [f for f, s in zip(frames, stale) if s]
        oldest_kept = max(w for w, s in zip(waited, stale) if not s)
        self._decide(now_ns, len(skipped), oldest_kept, bound)
        return kept, skipped

    def is_stale(self, ready_ns: int, now_ns: int) -> bool:
        """Whether a frame ready at ``ready_ns`` has waited beyond the bound at ``now_ns`` (a
        caller working through kept frames re-checks the ones a newer frame follows)."""
        bound = self.bound_ns()
        return bound is not None and int(now_ns) - int(ready_ns) > bound

    def is_late(self, ready_ns: int, now_ns: int) -> bool:
        """Whether a frame ready at ``ready_ns`` waited more than LATE_PERIODS frame periods at
        ``now_ns`` (never with keep_every_set, or before the period is known): a node that
        processes late frames more cheaply catches up before it has to skip any."""
        period = self.period_ns()
        if self.params.keep_every_set or period is None:
            return False
        return int(now_ns) - int(ready_ns) > LATE_PERIODS * period

    def skip(self, now_ns: int, n: int = 1) -> None:
        """``n`` frames skipped outside :meth:`select` (see :meth:`is_stale`)."""
        self._decide(int(now_ns), n, 0, self.bound_ns())

    def _decide(self, now_ns: int, skipped: int, backlog_ns: int, bound: int | None) -> None:
        self.skipped += skipped
        self._last_backlog_ns = backlog_ns
        self._max_backlog_ns = max(self._max_backlog_ns, backlog_ns)
        limit = bound if bound is not None else self._auto_bound()
        self._end_if_idle(now_ns)
        if skipped or backlog_ns > limit:
            if self._episode_start is None:
                self._episode_start = now_ns
        elif self._episode_start is not None and backlog_ns <= limit // 2:
            self._end_episode(now_ns)
        self._last_decision = now_ns

    def _auto_bound(self) -> int:
        """The bound a live node would use (what "behind" means with keep_every_set)."""
        period = self.period_ns() or 0
        return max(int(round(MIN_BACKLOG_S * 1e9)), int(BACKLOG_PERIODS * period))

    def _end_episode(self, end_ns: int) -> None:
        start = self._episode_start if self._episode_start is not None else end_ns
        length = max(0, end_ns - start)
        self._episodes += 1
        self._total_ns += length
        self._longest_ns = max(self._longest_ns, length)
        self._episode_start = None

    def _end_if_idle(self, now_ns: int) -> None:
        """An episode without decisions for IDLE_BOUNDS bounds (the input stopped) ended
        with its last decision."""
        if self._episode_start is None or self._last_decision is None:
            return
        idle = max(10**9, IDLE_BOUNDS * (self.bound_ns() or self._auto_bound()))
        if now_ns - self._last_decision > idle:
            self._end_episode(self._last_decision)

    # -- report ---------------------------------------------------------------------------
    def status(self, now_ns: int) -> BacklogStatus:
        """The state for /diagnostics at ``now_ns``; starts a new max-backlog interval."""
        self._end_if_idle(int(now_ns))
        current = 0 if self._episode_start is None else max(0, int(now_ns) - self._episode_start)
        bound = self.bound_ns()
        out = BacklogStatus(
            bound_s=float("nan") if bound is None else bound / 1e9,
            behind=self._episode_start is not None,
            behind_for_s=current / 1e9,
            episodes=self._episodes,
            behind_total_s=(self._total_ns + current) / 1e9,
            longest_s=max(self._longest_ns, current) / 1e9,
            last_backlog_s=self._last_backlog_ns / 1e9,
            max_backlog_s=self._max_backlog_ns / 1e9,
            skipped=self.skipped,
        )
        self._max_backlog_ns = 0
        return out


class LoadMeter:
    """A node's load: the share of the last ``window_s`` seconds of wall time its callbacks
    took (0..1; a callback still running counts up to ``now``). Wall time, not CPU time: a
    node that waits for a core is as busy for its input as one that computes. Times are ns
    on one monotonic clock.

    Why: a node near full load has no room for a slow frame, and the frame after it waits;
    the load says so before any frame has waited (is_late says so after)."""

    def __init__(self, window_s: float = LOAD_WINDOW_S):
        self.window_ns = int(round(window_s * 1e9))
        self._spans: deque[tuple[int, int]] = deque()  # closed callbacks (start, end), oldest first
        self._open: int | None = None  # start of the callback running now

    def begin(self, now_ns: int) -> None:
        """A callback starts (a nested one inside a running callback changes nothing)."""
        if self._open is None:
            self._open = int(now_ns)

    def end(self, now_ns: int) -> None:
        """The running callback ends."""
        if self._open is not None:
            self._spans.append((self._open, int(now_ns)))
            self._open = None

    def load(self, now_ns: int) -> float:
        """Busy share of the window ending at ``now_ns``."""
        now_ns = int(now_ns)
        start = now_ns - self.window_ns
        while self._spans and self._spans[0][1] <= start:
            self._spans.popleft()
        spans = list(self._spans) + ([(self._open, now_ns)] if self._open is not None else [])
        busy = sum(max(0, min(e, now_ns) - max(s, start)) for s, e in spans)
        return busy / self.window_ns
