"""Approximate-time synchroniser (core/sync.py) with an injected clock."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from maem_ros.core.sync import ApproximateTimeSync, FrameSet, SyncDrop

MS = 1_000_000
PERIOD = 33 * MS
T0 = 1_700_000_000_000_000_000
CAMS = ["cam0", "cam1", "cam2", "cam3"]


def make(**kw) -> ApproximateTimeSync:
    args = dict(slop_ns=20 * MS, max_wait_ns=150 * MS, min_cameras=2)
    args.update(kw)
    return ApproximateTimeSync(CAMS, **args)


def test_all_cameras_within_slop_emit_one_set() -> None:
    s = make()
    out = []
    for k, cam in enumerate(CAMS):
        out += s.add(cam, T0 + k * 3 * MS, f"{cam}@0", now_ns=T0 + 5 * MS + k * MS)
    assert len(out) == 1
    fs = out[0]
    assert isinstance(fs, FrameSet)
    assert fs.stamp_ns == T0 and fs.missing == []
    assert fs.items == {c: f"{c}@0" for c in CAMS}
    assert s.pending() == 0 and s.counters["sets"] == 1 and s.counters["partial_sets"] == 0


def test_set_waits_for_slow_camera_then_emits_when_complete() -> None:
    s = make()
    for cam in CAMS[:3]:
        assert s.add(cam, T0, cam, now_ns=T0 + MS) == []
    assert s.poll(T0 + 100 * MS) == []  # within max_wait: keep waiting
    out = s.add("cam3", T0 + 10 * MS, "cam3", now_ns=T0 + 120 * MS)
    assert len(out) == 1 and out[0].missing == []


@pytest.mark.parametrize("returning_first", [True, False])
def test_silent_camera_partial_after_max_wait_and_picked_up_again(returning_first: bool) -> None:
    s = make()
    sets: list[FrameSet] = []
    now = T0
    order = CAMS[::-1] if returning_first else CAMS
    # cam3 delivers frame 0 and then goes silent for frames 1..9, returning at frame 10
    for k in range(14):
        stamp = T0 + k * PERIOD
        now = stamp + 5 * MS
        for cam in order:
            if cam == "cam3" and 1 <= k <= 9:
                continue
            sets += s.add(cam, stamp, (cam, k), now_ns=now)
        sets += s.poll(now)
    sets += s.poll(now + 200 * MS)
    assert [fs.stamp_ns for fs in sets] == [T0 + k * PERIOD for k in range(14)]
    # a camera silent for > max_wait stops holding sets back; if its first message after
    # the gap arrives after the others' (returning_first False) that one frame misses it
    last_missing = 9 if returning_first else 10
    for k, fs in enumerate(sets):
        expected_missing = ["cam3"] if 1 <= k <= last_missing else []
        assert fs.missing == expected_missing, k
        assert set(fs.items) == set(CAMS) - set(expected_missing)
        assert all(item == (cam, k) for cam, item in fs.items.items())
    assert s.counters["partial_sets"] == last_missing
    assert s.counters["dropped_late"] == (0 if returning_first else 1)


def test_complete_only_poll_never_times_a_set_out() -> None:
    """A caller still taking messages polls complete_only: a set past max_wait that waits for
    a camera stays queued (its message may be among those not yet taken); complete sets and
    ones whose missing camera is already past them go out."""
    s = make()
    for cam in CAMS[:3]:
        s.add(cam, T0, cam, now_ns=T0 + MS, poll=False)
    late = T0 + 500 * MS
    assert s.poll(late, complete_only=True) == []
    s.add("cam3", T0 + PERIOD, "cam3@1", now_ns=late, poll=False)  # cam3 skipped frame 0
    out = s.poll(late, complete_only=True)
    assert [(fs.stamp_ns, fs.missing) for fs in out] == [(T0, ["cam3"])]
    for cam in CAMS[:3]:
        s.add(cam, T0 + PERIOD, f"{cam}@1", now_ns=late, poll=False)
    out = s.poll(late, complete_only=True)
    assert [(fs.stamp_ns, fs.missing) for fs in out] == [(T0 + PERIOD, [])]
    assert s.counters["timeouts"] == 0


def test_first_partial_set_only_after_max_wait() -> None:
    s = make()
    s.add("cam0", T0, "a", now_ns=T0)
    s.add("cam1", T0, "b", now_ns=T0)
    s.add("cam2", T0, "c", now_ns=T0)
    assert s.poll(T0 + 149 * MS) == []
    out = s.poll(T0 + 150 * MS)
    assert len(out) == 1 and out[0].missing == ["cam3"]


def test_camera_known_missing_when_its_next_frame_is_newer() -> None:
    s = make()
    for cam in CAMS[:3]:
        s.add(cam, T0, cam, now_ns=T0)
    # cam3's first message is a whole period later: it cannot belong to the set at T0
    out = s.add("cam3", T0 + PERIOD, "late-frame", now_ns=T0 + MS)
    assert len(out) == 1 and out[0].stamp_ns == T0 and out[0].missing == ["cam3"]
    assert s.pending() == 1


def test_too_few_cameras_dropped_and_counted() -> None:
    s = make(min_cameras=3)
    s.add("cam0", T0, "a", now_ns=T0)
    s.add("cam1", T0, "b", now_ns=T0)
    assert s.poll(T0 + 200 * MS) == []
    assert s.counters["dropped_too_few_cameras"] == 2 and s.pending() == 0


def test_stream_jumping_back_resets_once_and_keeps_the_new_frames() -> None:
    s = make()
    for k in range(3):
        for cam in CAMS:
            s.add(cam, T0 + k * PERIOD, k, now_ns=T0 + k * PERIOD)
    s.add("cam0", T0 + 3 * PERIOD, 3, now_ns=T0 + 3 * PERIOD)
    assert s.pending() == 1
    # bag loop: cam1 jumps back to the start; one camera alone is held aside, no reset
    assert s.add("cam1", T0, "loop", now_ns=T0 + 4 * PERIOD) == []
    assert s.stats.resets == 0 and s.pending() == 1
    out = []
    for cam in ["cam0", "cam2", "cam3"]:
        out += s.add(cam, T0 + 2 * MS, "loop", now_ns=T0 + 4 * PERIOD + MS)
    # three of four cameras jumped: one reset, cam0's queued frame 3 counted, held replayed
    assert s.stats.resets == 1 and s.stats.dropped[SyncDrop.RESET] == 1
    assert len(out) == 1 and out[0].stamp_ns == T0 and out[0].missing == []
    assert set(out[0].items.values()) == {"loop"}
    assert [e.kind for e in s.take_events()] == ["reset"]
    assert s.stats.dropped[SyncDrop.STALE] == 0


def test_small_step_back_and_duplicates_are_dropped() -> None:
    s = make()
    s.add("cam0", T0 + 10 * MS, "a", now_ns=T0)
    s.add("cam0", T0 + 5 * MS, "b", now_ns=T0)  # 5 ms back: within slop, not a loop
    s.add("cam0", T0 + 10 * MS, "c", now_ns=T0)  # repeated stamp
    assert s.counters["dropped_out_of_order"] == 2 and s.counters["resets"] == 0
    assert s.pending() == 1


def test_late_message_dropped() -> None:
    s = make()
    for cam in CAMS[:3]:
        s.add(cam, T0 + PERIOD, cam, now_ns=T0)
    assert len(s.poll(T0 + 200 * MS)) == 1  # emitted without cam3
    assert s.add("cam3", T0, "old", now_ns=T0 + 201 * MS) == []  # older than that set
    assert s.counters["dropped_late"] == 1 and s.pending() == 0


def test_bounded_memory() -> None:
    s = ApproximateTimeSync(CAMS, slop_ns=MS, max_wait_ns=10**12, min_cameras=4, queue_size=5)
    for k in range(50):  # only cam0 publishes and the wait never expires
        s.add("cam0", T0 + k * PERIOD, k, now_ns=T0 + k * PERIOD)
    assert s.pending() == 5 and s.counters["dropped_queue_full"] == 45


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="min_cameras"):
        ApproximateTimeSync(CAMS, 1, 1, min_cameras=5)
    with pytest.raises(ValueError, match="slop_ns"):
        ApproximateTimeSync(CAMS, -1, 1)
    with pytest.raises(ValueError, match="cameras"):
        ApproximateTimeSync(["a", "a"], 1, 1)
    with pytest.raises(ValueError, match="camera"):
        make().add("nope", T0, None, now_ns=T0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), jitter_ms=st.integers(0, 8), latency_ms=st.integers(0, 60))
def test_jittered_stamps_form_complete_sets(seed: int, jitter_ms: int, latency_ms: int) -> None:
    """Per-camera stamp jitter below slop/2 and random delivery latency: every frame complete."""
    rng = np.random.default_rng(seed)
    s = make()
    frames = 30
    msgs = []
    last_arrival = dict.fromkeys(CAMS, 0)
    for k in range(frames):
        for cam in CAMS:
            stamp = T0 + k * PERIOD + int(rng.integers(-jitter_ms, jitter_ms + 1)) * MS
            # one FIFO transport per camera: a message never overtakes the previous one
            arrival = max(stamp + int(rng.integers(0, latency_ms + 1)) * MS, last_arrival[cam] + 1)
            last_arrival[cam] = arrival
            msgs.append((arrival, stamp, cam, k))
    msgs.sort()
    sets = []
    for arrival, stamp, cam, k in msgs:
        sets += s.add(cam, stamp, k, now_ns=arrival)
    sets += s.poll(msgs[-1][0] + 10**9)
    assert len(sets) == frames
    for k, fs in enumerate(sets):
        assert fs.missing == [] and set(fs.items.values()) == {k}


def test_frame_period_longer_than_max_wait_still_gives_complete_sets() -> None:
    """Slow replay (period 400 ms > max_wait 150 ms) with cameras arriving 30 ms apart: no
    camera is taken for dead just because the previous frame was long ago."""
    s = make()
    period = 400 * MS
    out: list[FrameSet] = []
    for frame in range(5):
        for k, cam in enumerate(CAMS):
            t = T0 + frame * period
            out += s.add(cam, t, (cam, frame), now_ns=t + 10 * MS + k * 30 * MS)
    assert len(out) == 5
    assert all(fs.missing == [] for fs in out)
    assert s.counters["dropped_too_few_cameras"] == 0 and s.counters["dropped_late"] == 0


def test_dead_camera_costs_max_wait_on_a_few_sets_only() -> None:
    """A camera silent for dead_after_sets sets is no longer waited for."""
    s = make(dead_after_sets=2)
    waited = []
    for frame in range(4):
        t = T0 + frame * PERIOD
        now = T0 + frame * 400 * MS
        out = []
        for cam in CAMS[:3]:
            out += s.add(cam, t, cam, now_ns=now + MS)
        if not out:  # still waiting for cam3: only max_wait releases the set
            out = s.poll(now + 200 * MS)
            waited.append(frame)
        assert [fs.missing for fs in out] == [["cam3"]]
    assert waited == [0, 1]


def test_lagging_camera_is_still_waited_for() -> None:
    """cam3 starts 1.5 s late (slow start-up) and then catches up, one frame at a time
    (each of its messages >= 41 ms after the previous). Only frame 0 exceeds max_wait; the
    later frames are complete because a camera that missed one set is still waited for
    (stopping to wait after a single missed set lost frames 1 and 2 here)."""
    s = make(max_wait_ns=1000 * MS)
    period = 667 * MS
    lag_ms = [1500, 874, 248, 20, 20, 20]
    events = []  # (arrival ns, camera or None for a poll, stamp ns)
    for frame, lag in enumerate(lag_ms):
        t = T0 + frame * period
        events += [(t + MS, cam, t) for cam in CAMS[:3]]
        events += [(t + lag * MS, "cam3", t), (t + 1001 * MS, None, t)]
    sets: list[FrameSet] = []
    for now, cam, stamp in sorted(events, key=lambda e: e[0]):
        sets += s.poll(now) if cam is None else s.add(cam, stamp, cam, now_ns=now)
    assert [fs.missing for fs in sets] == [["cam3"], [], [], [], [], []]


def run_stream(s: ApproximateTimeSync, frames: int, arrival, extra=()) -> list[FrameSet]:
    """Feed ``frames`` frames of every camera in arrival order; ``arrival(cam, k)`` -> ns after
    the stamp (None = not sent); ``extra`` = (arrival ns, cam, stamp ns) hostile messages."""
    events = [(T0 + k * PERIOD + arrival(c, k), c, T0 + k * PERIOD, (c, k))
              for k in range(frames) for c in CAMS if arrival(c, k) is not None]
    events += [(t, c, st, "hostile") for t, c, st in extra]
    events.sort(key=lambda e: e[0])
    out: list[FrameSet] = []
    for t, cam, stamp, item in events:
        out += s.poll(t)
        out += s.add(cam, stamp, item, now_ns=t)
    return out + s.poll(events[-1][0] + 10**10)


def test_camera_300ms_late_stops_holding_back_the_others_and_rejoins() -> None:
    s = make()
    lag_ms = lambda c, k: 300 if c == "cam3" and k < 60 else (c == "cam3") * 2 + 1  # noqa: E731
    sets = run_stream(s, 90, lambda c, k: lag_ms(c, k) * MS)
    assert [fs.stamp_ns for fs in sets] == [T0 + k * PERIOD for k in range(90)]
    without = [k for k, fs in enumerate(sets) if fs.missing == ["cam3"]]
    # the first frames wait max_wait for cam3 until two late messages show its lag; then none
    assert without[0] == 0 and without == list(range(without[-1] + 1))
    assert 55 <= len(without) <= 62
    assert all(fs.missing == [] for fs in sets[without[-1] + 1:])
    # every cam3 message missing from a set is counted: lagging, late, or overtaken by
    # frame 60 (sent with the short lag) and so out of order
    assert s.stats.total_dropped == len(without)
    assert s.stats.dropped[SyncDrop.LAGGING] >= 45
    kinds = [(e.kind, e.camera) for e in s.take_events()]
    assert kinds == [("lagging", "cam3"), ("rejoined", "cam3")]


def test_lagging_camera_costs_the_others_no_latency() -> None:
    """Release time of each set (the poll that emits it) vs its stamp: bounded by one
    max_wait for the first few frames, then the normal arrival latency."""
    s = make()
    released = []
    events = sorted((T0 + k * PERIOD + (300 if c == "cam3" else 1) * MS, c, T0 + k * PERIOD)
                    for k in range(60) for c in CAMS)
    for t, cam, stamp in events:
        for fs in s.poll(t) + s.add(cam, stamp, cam, now_ns=t):
            released.append(t - fs.stamp_ns)
    assert len(released) >= 59
    assert max(released) <= 150 * MS + PERIOD  # polled at arrivals only: one period granular
    assert max(released[12:]) <= 1 * MS  # no waiting once the lag is known


def test_max_lag_compensates_a_constant_lag() -> None:
    s = make(max_lag_ns=400 * MS)
    sets = run_stream(s, 40, lambda c, k: (300 if c == "cam3" else 1) * MS)
    # the first sets go without cam3 (its lag is measured on two messages, 300 ms after their
    # stamps, and by then it has missed dead_after_sets sets), then it is waited for
    assert all(fs.missing == [] for fs in sets[12:]) and len(sets) == 40
    assert s.stats.total_dropped == sum(bool(fs.missing) for fs in sets)
    assert s.lagging() == {}


@pytest.mark.parametrize("stamp_of", [lambda k: 0, lambda k: T0 + (k - 30) * PERIOD,
                                      lambda k: T0 + (k - 1) * PERIOD,
                                      lambda k: T0 + 10**12 + k])
def test_hostile_stamps_from_one_camera_cost_no_frames(stamp_of) -> None:
    """Stamp 0, a 1 s old duplicate, a previous frame, a far-future stamp: every 10th frame
    cam2 sends one extra such message; all frames stay complete, no reset, each counted."""
    s = make()
    extra = [(T0 + k * PERIOD + 2 * MS, "cam2", stamp_of(k)) for k in range(5, 60, 10)]
    sets = run_stream(s, 60, lambda c, k: MS, extra)
    assert len(sets) == 60 and all(fs.missing == [] for fs in sets)
    assert all("hostile" not in fs.items.values() for fs in sets)
    assert s.stats.resets == 0
    assert s.stats.total_dropped == len(extra)
    assert s.stats.received == 60 * 4 + len(extra)


def test_held_stale_stamps_are_counted_when_released() -> None:
    s = make()
    for k in range(3):
        for cam in CAMS:
            s.add(cam, T0 + k * PERIOD, k, now_ns=T0 + k * PERIOD + MS)
    s.add("cam1", 0, "zero", now_ns=T0 + 3 * PERIOD)
    assert s.stats.total_dropped == 0  # held: it might be the start of a loop
    s.add("cam1", T0 + 3 * PERIOD, 3, now_ns=T0 + 3 * PERIOD + MS)
    assert s.stats.dropped[SyncDrop.STALE] == 1


def test_future_first_message_does_not_poison_the_others() -> None:
    """cam0's very first stamp is far in the future (nobody to compare with): once the
    others run, its valid stamps re-anchor it and every camera is in the sets."""
    s = make()
    s.add("cam0", T0 + 10**12, "future", now_ns=T0)
    sets = run_stream(s, 20, lambda c, k: MS)
    assert len(sets) >= 19 and all(fs.missing == [] for fs in sets[2:])
    assert "future" not in [v for fs in sets for v in fs.items.values()]


# ---- StampGuard (one stream: the triangulation node's clusters) ---------------------------------
from maem_ros.core.sync import StampGuard  # noqa: E402


def push_all(g: StampGuard, stamps):
    accepted, dropped, jumps = [], [], 0
    for s in stamps:
        r = g.push(s, s)
        accepted += [st for st, _ in r.accepted]
        dropped += r.dropped
        jumps += r.jumped_back
    return accepted, dropped, jumps


def test_stamp_guard_drops_isolated_hostile_stamps() -> None:
    ok = [T0 + k * PERIOD for k in range(10)]
    stream = ok[:3] + [0] + ok[3:5] + [ok[4]] + ok[5:7] + [T0 + 10**15] + ok[7:]
    accepted, dropped, jumps = push_all(StampGuard(), stream)
    assert accepted == ok and jumps == 0
    assert [r for r, _ in dropped] == ["stale_stamp", "duplicate_stamp", "future_stamp"]


def test_stamp_guard_confirms_a_loop_and_loses_nothing() -> None:
    first = [T0 + k * PERIOD for k in range(6)]
    loop = [T0 + k * PERIOD for k in range(5)]
    accepted, dropped, jumps = push_all(StampGuard(confirm=2), first + loop)
    assert accepted == first + loop and dropped == [] and jumps == 1
    # a forward jump (pause, seek) is confirmed too, without a reset
    later = [T0 + 10**12 + k * PERIOD for k in range(4)]
    g = StampGuard()
    accepted, dropped, jumps = push_all(g, first + later)
    assert accepted == first + later and jumps == 0 and g.last == later[-1]


def test_stamp_guard_slow_stream_is_not_a_jump() -> None:
    """A 0.5 fps stream (2 s between frames > jump_ns 1 s): the bound grows with the time
    between messages, so every frame goes through at once; a far-future stamp still does not."""
    g = StampGuard(jump_ns=10**9)
    period = 2 * 10**9
    for k in range(5):
        r = g.push(T0 + k * period, k, now_ns=T0 + k * period + 5 * MS)
        assert [it for _, it in r.accepted] == [k] and not r.dropped
    assert g.push(T0 + 10**15, "future", now_ns=T0 + 5 * period).accepted == []
    r = g.push(T0 + 5 * period, 5, now_ns=T0 + 5 * period + 5 * MS)
    assert [it for _, it in r.accepted] == [5] and r.dropped == [("future_stamp", "future")]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 40), min_size=1, max_size=60))
def test_stamp_guard_output_is_strictly_increasing_between_jumps(steps) -> None:
    """Whatever comes in, accepted stamps only go back at a confirmed jump, and every input
    is accepted, dropped or still held."""
    g = StampGuard(jump_ns=10 * MS, confirm=2)
    stamps = [T0 + s * MS for s in steps]
    out, n_dropped = [], 0
    for s in stamps:
        r = g.push(s, s)
        if r.jumped_back:
            out.append(None)
        out += [st for st, _ in r.accepted]
        n_dropped += len(r.dropped)
    runs, cur = [], []
    for v in out:
        if v is None:
            runs.append(cur)
            cur = []
        else:
            cur.append(v)
    runs.append(cur)
    for run in runs:
        assert all(b > a for a, b in zip(run, run[1:])), out
    held = len(g._held)
    assert sum(len(r) for r in runs) + n_dropped + held == len(stamps)


def test_lag_fluctuating_around_the_window_does_not_flap() -> None:
    """cam3's lag cycles between 140 and 200 ms around max_wait 150 ms (in order: each
    message after the previous): once lagging it stays so (it would rejoin below 75 ms), so
    the sets are not held back whenever its lag dips under the window."""
    s = make()
    cycle = (170, 200, 180, 160, 140, 160, 190)
    sets = run_stream(s, 63, lambda c, k: (cycle[k % 7] if c == "cam3" else 1) * MS)
    kinds = [e.kind for e in s.take_events()]
    assert kinds.count("lagging") == 1 and "rejoined" not in kinds
    assert s.stats.timeouts <= 6 and len(sets) == 63


def busy_node(drain: bool, frames: int = 40, stall_at: int = 10, stall_ms: int = 400,
              work_ms: int = 20) -> tuple[ApproximateTimeSync, list[FrameSet]]:
    """A node modelled as its executor runs it: camera i's message of frame k reaches the
    process at stamp + 2 + i ms (the rmw receive time); the node takes messages only when it
    is idle; each set costs ``work_ms`` of association, set ``stall_at`` stalls ``stall_ms``
    (CPU starvation). ``drain``: take every received message (``poll=False``), then poll once;
    else take one message and poll (the synchroniser decides with messages still queued)."""
    s = make()
    msgs = sorted((T0 + k * PERIOD + (2 + i) * MS, cam, T0 + k * PERIOD)
                  for k in range(frames) for i, cam in enumerate(CAMS))
    sets: list[FrameSet] = []
    now, idx = msgs[0][0], 0
    while idx < len(msgs):
        now = max(now, msgs[idx][0])  # idle until the next message arrives
        out: list[FrameSet] = []
        if drain:
            while idx < len(msgs) and msgs[idx][0] <= now:
                received, cam, stamp = msgs[idx]
                out += s.add(cam, stamp, (cam, stamp), now, arrival_ns=received, poll=False)
                idx += 1
            out += s.poll(now)
        else:
            received, cam, stamp = msgs[idx]
            out += s.add(cam, stamp, (cam, stamp), now, arrival_ns=received)
            idx += 1
        for fs in out:
            sets.append(fs)
            now += (stall_ms if len(sets) == stall_at else work_ms) * MS
    return s, sets + s.poll(now + 10**10)


def test_busy_node_that_takes_everything_pending_first_loses_no_camera() -> None:
    """After a 400 ms stall twelve frames wait in the queues, their receive times long past
    max_wait: taken all before the decision, every set is complete."""
    s, sets = busy_node(drain=True)
    assert [fs.stamp_ns for fs in sets] == [T0 + k * PERIOD for k in range(40)]
    assert all(fs.missing == [] for fs in sets)
    assert s.stats.total_dropped == 0 and s.stats.timeouts == 0 and s.lagging() == {}


def test_busy_node_deciding_between_takes_loses_the_backlog() -> None:
    """The same stall, deciding after every message taken: each queued frame's first message
    is already older than max_wait, its set goes out with that camera alone (too few) or
    partial. This is why the node drains before it polls."""
    s, sets = busy_node(drain=False)
    lost = 40 - sum(not fs.missing for fs in sets)
    assert lost >= 5
    assert s.stats.dropped[SyncDrop.TOO_FEW_CAMERAS] + s.stats.partial_sets >= 5


def test_arrival_after_now_is_clamped_to_now() -> None:
    """A receive time later than the caller's clock (clock mismatch) counts as now: the set
    still waits max_wait from there."""
    s = make()
    for cam in CAMS[:3]:
        s.add(cam, T0, cam, T0, arrival_ns=T0 + 10**9)
    assert s.poll(T0 + 149 * MS) == []
    assert [fs.missing for fs in s.poll(T0 + 150 * MS)] == [["cam3"]]


def test_ready_time_is_the_last_arrival_or_the_wait_deadline_not_when_polled() -> None:
    """A complete set is ready when its last message arrived; a set missing a camera when its
    max_wait ran out, however late the caller polls: what the caller's backlog is measured
    from."""
    s = make()
    for k, cam in enumerate(CAMS):
        s.add(cam, T0, cam, now_ns=T0 + 40 * MS, arrival_ns=T0 + (5 + k) * MS, poll=False)
    (complete,) = s.poll(T0 + 40 * MS)
    assert complete.ready_ns == T0 + 8 * MS
    stamps = [T0 + PERIOD, T0 + 2 * PERIOD]
    for t in stamps:  # cam3 goes silent
        for cam in CAMS[:3]:
            s.add(cam, t, cam, now_ns=t + 2 * MS, arrival_ns=t + 2 * MS)
    assert s.poll(stamps[0] + 100 * MS) == []
    late = s.poll(stamps[1] + 400 * MS)  # the caller polls late
    assert [fs.stamp_ns for fs in late] == stamps
    assert [fs.missing for fs in late] == [["cam3"], ["cam3"]]
    assert [fs.ready_ns for fs in late] == [t + 2 * MS + 150 * MS for t in stamps]
