"""CPU time (ms per frame set) of the association node's work on the live benchmark's scene
(config/demo.yaml, 6 cameras, f32 full mesh or q4), as the node does it but without DDS:
check (read, limits, and for f32 the gate preparation that checks the vertices), decode + gate
preparation (q4), the track-assisted association step, the
clusters encoding. Frames are stamped at 60 fps.

    python scripts/live_set_time.py f32|q4 [FRAMES] [--prof [tottime|cumulative]]
"""

import cProfile
import pstats
import sys
import time

from demo_sets import demo_sets

from maem_ros.core.association import AssociationParams
from maem_ros.core.limits import InputLimits
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
from maem_ros.ros import wire
from maem_ros.ros.association_node import checked_detections, prepared_detections

layout = sys.argv[1] if len(sys.argv) > 1 else "f32"
frames = int(sys.argv[2]) if len(sys.argv) > 2 and sys.argv[2].isdigit() else 120
scene, p, rig, msgs = demo_sets(layout, frames)
stage = TemporalAssociator(rig, AssociationParams.from_mapping(p), TemporalParams.from_mapping(p))
limits = InputLimits()
totals = {"check": 0.0, "decode": 0.0, "step": 0.0, "encode": 0.0}


def one(f: int) -> None:
    stamp = int(f * 1e9 / 60)
    t0 = time.process_time()
    read = {c: checked_detections(m, f"/{c}/detections", c, rig, limits, stage.gates) for c, m in msgs[f]}
    t1 = time.process_time()
    items = {c: prepared_detections(m, stage.gates) for c, m in read.items()}
    t2 = time.process_time()
    res = stage.step(items, stamp)
    t3 = time.process_time()
    wire.clusters_to_msg(stamp, "world", rig, items, res.clusters, res.track_ids, res.flags)
    t4 = time.process_time()
    for k, a, b in (("check", t0, t1), ("decode", t1, t2), ("step", t2, t3), ("encode", t3, t4)):
        totals[k] += b - a


for f in range(10):  # warm: tracks confirmed, caches filled
    one(f)
for k in totals:
    totals[k] = 0.0
prof = cProfile.Profile() if "--prof" in sys.argv else None
if prof:
    prof.enable()
for f in range(10, len(msgs)):
    one(f)
if prof:
    prof.disable()
    order = sys.argv[-1] if sys.argv[-1] in ("tottime", "cumulative") else "cumulative"
    pstats.Stats(prof).sort_stats(order).print_stats(40)
n = len(msgs) - 10
print(layout, {k: round(v / n * 1e3, 2) for k, v in totals.items()}, "ms CPU per set")
