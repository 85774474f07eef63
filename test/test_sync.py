"""Approximate-time synchroniser (core/sync.py) with an injected clock."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from maem_ros.core.sync import ApproximateTimeSync, FrameSet

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


def test_stamps_backwards_reset() -> None:
    s = make()
    for k in range(3):
        for cam in CAMS:
            s.add(cam, T0 + k * PERIOD, k, now_ns=T0 + k * PERIOD)
    s.add("cam0", T0 + 3 * PERIOD, 3, now_ns=T0 + 3 * PERIOD)
    assert s.pending() == 1
    # bag loop: cam1 jumps back to the start; the queues are cleared, new sets flow
    assert s.add("cam1", T0, "loop", now_ns=T0 + 4 * PERIOD) == []
    assert s.counters["resets"] == 1 and s.pending() == 1
    out = []
    for cam in ["cam0", "cam2", "cam3"]:
        out += s.add(cam, T0 + 2 * MS, "loop", now_ns=T0 + 4 * PERIOD + MS)
    assert len(out) == 1 and out[0].stamp_ns == T0 and out[0].missing == []


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
