"""The fault schedule, the synchroniser model and the soak's message balance (tools)."""
from __future__ import annotations

from maem_ros.tools.bench.latency import Faults, sync_model
from maem_ros.tools.bench.soak import balance

CAMS = [f"camera_{i}" for i in range(6)]


def test_fault_schedule():
    stamps = [10**18 + k * 33_333_333 for k in range(60)]
    ev = Faults("camera_5", 0.3, 1.0).schedule(stamps, CAMS, 30.0)
    assert [t for t, _, _ in ev] == sorted(t for t, _, _ in ev)
    late = [(t, s) for t, s, c in ev if c == ("camera_5",)]
    assert len(late) == 60 and all(abs(t - (stamps.index(s) / 30 + 0.3)) < 1e-9 for t, s in late)
    stale = [s for _, s, c in ev if c == ("camera_0",)]  # one extra message per second
    assert stale == [0]  # the first is stamp 0, the next (at 2 s) a 1 s old duplicate
    long = Faults(stale_every_s=1.0).schedule(stamps * 3, CAMS, 30.0)
    assert [s for _, s, c in long if c == ("camera_0",)][:2] == [0, stamps[30]]


def test_sync_model_meets_the_lag_and_stale_targets():
    """The synchroniser alone: one camera 300 ms late leaves the other cameras' frame latency
    within 20 ms of a clean run and loses < 1 % of frames; stale stamps every second cost none."""
    clean = sync_model(CAMS, 600, 30.0, Faults())
    lag = sync_model(CAMS, 600, 30.0, Faults("camera_5", 0.3))
    stale = sync_model(CAMS, 600, 30.0, Faults(stale_every_s=1.0))
    assert clean["frames_without_set"] == 0 and clean["missing_slots"] == {}
    assert abs(lag["latency_ms_median"] - clean["latency_ms_median"]) < 20.0, (clean, lag)
    assert lag["frames_without_set"] < 0.01 * 600
    assert set(lag["missing_slots"]) == {"camera_5"}
    assert stale["frames_without_set"] == 0 and stale["missing_slots"] == {}
    assert sum(stale["dropped"].values()) >= 19


def test_balance_counts_what_no_node_explains():
    d = {f"/{c}/frontend": {f"received/{c}/image_raw": "10", "frames_processed": "9",
                            "frames_dropped": "1"} for c in CAMS}
    d["/association"] = {**{f"received/{c}/detections": "9" for c in CAMS},
                         "count/sync_sets": "9", "frames_processed": "9", "frames_dropped": "0"}
    d["/triangulation"] = {"received/maem/clusters": "9", "frames_processed": "9",
                           "frames_dropped": "0"}
    assert set(balance(d, CAMS, 10, 9).values()) == {0}
    d["/association"]["received/camera_3/detections"] = "8"  # one detections message vanished
    bal = balance(d, CAMS, 10, 9)
    assert bal["frontends->association"] == 1 and bal["association"] == -1
