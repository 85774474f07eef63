"""The live overload policy (core/backlog.py) with an injected clock."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings, strategies as st

from maem_ros.core.backlog import (BACKLOG_PERIODS, LATE_PERIODS, LOAD_WINDOW_S, MIN_BACKLOG_S,
                                   Backlog, BacklogParams, LoadMeter)

MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def fed(rate_hz: float, frames: int = 40, **params) -> Backlog:
    """A policy that has seen ``frames`` stamps at ``rate_hz``."""
    b = Backlog(BacklogParams(**params))
    for k in range(frames):
        b.observe(T0 + int(round(k * 1e9 / rate_hz)))
    return b


def test_the_automatic_bound_follows_the_frame_rate() -> None:
    assert Backlog(BacklogParams()).bound_ns() == int(MIN_BACKLOG_S * 1e9)  # rate unknown yet
    assert fed(60).bound_ns() == pytest.approx(BACKLOG_PERIODS * 1e9 / 60, abs=MS)
    assert fed(30).bound_ns() == pytest.approx(BACKLOG_PERIODS * 1e9 / 30, abs=MS)
    assert fed(200).bound_ns() == int(MIN_BACKLOG_S * 1e9)  # the floor
    assert fed(60, max_backlog=0.25).bound_ns() == 250 * MS
    assert fed(60, keep_every_set=True).bound_ns() is None


def test_the_frame_period_ignores_repeats_and_restarts_after_a_loop() -> None:
    b = fed(30, frames=10)
    b.observe(T0 + int(round(9 * 1e9 / 30)))  # the same frame again: no interval
    assert b.period_ns() == pytest.approx(33_333_333, abs=1)
    b.observe(T0)  # the bag looped
    assert b.period_ns() is None
    for k in range(1, 5):
        b.observe(T0 + k * 20 * MS)
    assert b.period_ns() == 20 * MS


def test_a_node_behind_catches_up_to_the_newest_frame() -> None:
    b = fed(60)  # bound ~66.7 ms
    now = T0 + 10**9
    frames = ["a", "b", "c", "d", "e"]
    waited_ms = [300, 200, 100, 40, 5]
    kept, skipped = b.select(frames, [now - w * MS for w in waited_ms], now)
    assert kept == ["e"] and skipped == ["a", "b", "c", "d"]
    kept, skipped = b.select(["x", "y"], [now - 900 * MS, now - 800 * MS], now)
    assert kept == ["y"] and skipped == ["x"]  # everything stale: the newest still goes
    assert b.skipped == 5
    kept, skipped = b.select(["p", "q", "r"], [now - 60 * MS, now - 30 * MS, now], now)
    assert kept == ["p", "q", "r"] and skipped == []  # within the bound: worked through


def test_catch_up_stale_skips_only_the_frames_beyond_the_bound() -> None:
    b = fed(60, catch_up="stale")
    now = T0 + 10**9
    frames = ["a", "b", "c", "d", "e"]
    waited_ms = [300, 200, 100, 40, 5]
    kept, skipped = b.select(frames, [now - w * MS for w in waited_ms], now)
    assert kept == ["d", "e"] and skipped == ["a", "b", "c"]
    assert b.skipped == 3
    kept, skipped = fed(60, keep_every_set=True).select(frames, [now - w * MS for w in
                                                                 waited_ms], now)
    assert kept == frames and skipped == []


def test_a_frame_that_went_stale_while_others_were_processed() -> None:
    b = fed(30)  # bound ~133 ms
    assert not b.is_stale(T0, T0 + 130 * MS) and b.is_stale(T0, T0 + 140 * MS)
    assert not fed(30, keep_every_set=True).is_stale(T0, T0 + 10**10)


def test_an_episode_behind_lasts_from_the_first_skip_until_the_backlog_is_low_again() -> None:
    b = fed(60)
    t = T0 + 10**9
    b.select(["f"], [t - 5 * MS], t)
    st0 = b.status(t)
    assert not st0.behind and st0.episodes == 0 and st0.behind_for_s == 0
    b.select(["a", "b"], [t + 100 * MS - 600 * MS, t + 100 * MS - MS], t + 100 * MS)
    st1 = b.status(t + 300 * MS)
    assert st1.behind and st1.behind_for_s == pytest.approx(0.2)
    assert st1.max_backlog_s == pytest.approx(0.001)  # the kept one's wait, not the skipped
    b.select(["c"], [t + 400 * MS - 60 * MS], t + 400 * MS)  # still above half the bound
    assert b.status(t + 400 * MS).behind
    b.select(["d"], [t + 500 * MS - 10 * MS], t + 500 * MS)  # caught up
    st2 = b.status(t + 600 * MS)
    assert not st2.behind and st2.episodes == 1 and st2.behind_for_s == 0
    assert st2.longest_s == pytest.approx(0.4) and st2.behind_total_s == pytest.approx(0.4)
    assert st2.skipped == 1


def test_keep_every_set_still_reports_being_behind() -> None:
    """Nothing is skipped, but a node working on frames older than a live node's bound is
    behind (for how long is in /diagnostics)."""
    b = fed(60, keep_every_set=True)
    t = T0 + 10**9
    b.select(["a", "b"], [t - 500 * MS, t - 480 * MS], t)
    st1 = b.status(t + 100 * MS)
    assert st1.behind and math.isnan(st1.bound_s) and st1.last_backlog_s == pytest.approx(0.5)
    assert st1.skipped == 0


def test_an_episode_ends_when_the_input_stops() -> None:
    b = fed(60)
    t = T0 + 10**9
    b.select(["a", "b"], [t - 500 * MS, t], t)
    assert b.status(t + 100 * MS).behind
    st1 = b.status(t + 5 * 10**9)
    assert not st1.behind and st1.episodes == 1 and st1.longest_s == 0


@settings(max_examples=200, deadline=None)
@given(waited=st.lists(st.integers(0, 2000), min_size=1, max_size=40),
       bound_ms=st.integers(1, 500), catch_up=st.sampled_from(["newest", "stale"]))
def test_selection_keeps_order_the_newest_and_exactly_the_fresh_ones(waited, bound_ms,
                                                                       catch_up) -> None:
    b = Backlog(BacklogParams(max_backlog=bound_ms / 1e3, catch_up=catch_up))
    now = T0 + 10**10
    frames = list(range(len(waited)))
    kept, skipped = b.select(frames, [now - w * MS for w in waited], now)
    assert sorted(kept + skipped) == frames and kept == sorted(kept)
    assert kept[-1] == frames[-1]
    assert all(waited[k] <= bound_ms for k in kept[:-1])
    behind = any(w > bound_ms for w in waited[:-1])
    if catch_up == "stale" or not behind:
        assert all(waited[k] > bound_ms for k in skipped)
    else:
        assert kept == frames[-1:]
    assert b.skipped == len(skipped)


def test_bad_parameters_name_the_parameter() -> None:
    with pytest.raises(ValueError, match="max_backlog"):
        BacklogParams(max_backlog=-0.1)
    with pytest.raises(ValueError, match="keep_every_set"):
        BacklogParams(keep_every_set="yes")


class _Clock:
    """A node's clock and logger, as NodeBacklog reads them (injected time, ns)."""

    def __init__(self, now_ns: int):
        self.now_ns = now_ns

    def get_clock(self):
        return self

    def now(self):
        return self

    @property
    def nanoseconds(self) -> int:
        return self.now_ns

    def get_logger(self):
        return self

    def info(self, text: str) -> None:
        pass


class _Diagnostics:
    """Counts what NodeBacklog rejects (dropped/<reason>)."""

    def __init__(self) -> None:
        self.rejected: dict[str, int] = {}

    def add_source(self, source) -> None:
        pass

    def reject(self, reason: str, text: str, log_period_s: float = 1.0, n: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + n


@pytest.mark.parametrize("catch_up, processed", [("newest", ["a", "d"]),
                                                 ("stale", ["a", "c", "d"])])
def test_frames_going_stale_while_a_batch_is_processed(catch_up, processed) -> None:
    """A batch kept at once (none stale yet) whose frames go stale while the node works: with
    catch_up newest, once one is found stale the rest up to the newest are skipped too."""
    from maem_ros.ros.overload import NodeBacklog

    clock, diag = _Clock(T0 + 10**9), _Diagnostics()
    nb = NodeBacklog(clock, diag, BacklogParams(max_backlog=0.1, catch_up=catch_up), "sets")
    waited = {"a": 90, "b": 60, "c": 30, "d": 0}  # ms at the decision; bound 100 ms
    start = clock.now_ns
    frames = list(waited)
    ready = {f: start - w * MS for f, w in waited.items()}
    kept = nb.select(frames, [ready[f] for f in frames], list(range(4)))
    assert kept == frames  # none waited beyond the bound yet
    done = []
    for k, f in enumerate(kept):
        if nb.still_fresh(ready[f], k, k < len(kept) - 1):
            done.append(f)
            clock.now_ns += 50 * MS  # each frame takes the node 50 ms
    # b has waited 110 ms when its turn comes: skipped; c 80 ms: worked through only with stale
    assert done == processed
    assert diag.rejected["behind"] == 4 - len(processed)


def test_a_frame_is_late_once_it_waited_more_than_a_frame_period() -> None:
    """is_late: the node is falling behind (a frame waited beyond LATE_PERIODS periods), long
    before the bound makes it skip; never with keep_every_set or before the rate is known."""
    b = fed(60)  # period ~16.7 ms
    ready = T0 + 10**9
    assert not b.is_late(ready, ready + int(LATE_PERIODS * 16 * MS))
    assert b.is_late(ready, ready + int(LATE_PERIODS * 18 * MS))
    assert not b.is_stale(ready, ready + int(LATE_PERIODS * 18 * MS))
    assert not fed(60, keep_every_set=True).is_late(ready, ready + 10**9)
    assert not Backlog(BacklogParams()).is_late(ready, ready + 10**9)


def test_the_load_is_the_callbacks_share_of_the_window() -> None:
    """LoadMeter: busy time inside the last window / the window; a span crossing the window's
    start counts its part inside, a running callback counts up to now, a nested begin is the
    outer callback's."""
    meter = LoadMeter(0.25)
    assert meter.window_ns == 250 * MS and LoadMeter().window_ns == int(LOAD_WINDOW_S * 1e9)
    assert meter.load(T0) == 0.0
    for start, end in ((-60, 40), (100, 150)):  # ms from T0
        meter.begin(T0 + start * MS)
        meter.begin(T0 + (start + 5) * MS)  # nested: ignored
        meter.end(T0 + end * MS)
    meter.end(T0 + 160 * MS)  # nothing running: ignored
    assert meter.load(T0 + 150 * MS) == pytest.approx((60 + 40 + 50) / 250)
    # the window [-10, 240] ms: 50 ms of the first span, all of the second
    assert meter.load(T0 + 240 * MS) == pytest.approx((50 + 50) / 250)
    meter.begin(T0 + 200 * MS)  # running for 100 ms at 300 ms
    assert meter.load(T0 + 300 * MS) == pytest.approx((50 + 100) / 250)
    assert meter.load(T0 + 10**9) == pytest.approx(1.0)  # running the whole window
    meter.end(T0 + 10**9)
    assert meter.load(T0 + 2 * 10**9) == 0.0


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)), min_size=1, max_size=60))
def test_the_load_lies_between_0_and_1(gaps_and_lengths: list[tuple[int, int]]) -> None:
    """Whatever the callbacks (one after the other, ms apart, ms long), the load is a share of
    the window, and equals the busy time counted directly."""
    meter, t, spans = LoadMeter(0.1), T0, []
    for gap, length in gaps_and_lengths:
        t += gap * MS
        meter.begin(t)
        meter.end(t + length * MS)
        spans.append((t, t + length * MS))
        t += length * MS
        start = t - 100 * MS
        busy = sum(max(0, min(e, t) - max(s, start)) for s, e in spans)
        assert 0.0 <= meter.load(t) <= 1.0
        assert meter.load(t) == pytest.approx(busy / (100 * MS))
