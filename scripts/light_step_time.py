"""The association's light step against its full step, offline, on the live benchmark's scene
(config/demo.yaml, 6 cameras, 60 fps stamps): CPU per frame set (check + decode + step, as the
association node does them, without DDS) and what each finds (clusters, clusters mixing
people, member views), for the full step, the light step that associates new people on every
set (``light_new_every: 0``) and the default light step (new people every
``light_new_every`` s, no mesh decoded in between). The first 10 sets run full (tracks).

    python scripts/light_step_time.py q4|f32
"""

import sys
import time

from demo_sets import demo_sets

from maem_ros.core.association import AssociationParams
from maem_ros.core.limits import InputLimits
from maem_ros.core.tracking.temporal import TemporalAssociator, TemporalParams
from maem_ros.ros.association_node import checked_detections, prepared_detections

WARM = 10  # full steps first: tracks confirmed
layout = sys.argv[1] if len(sys.argv) > 1 else "q4"
scene, p, rig, msgs = demo_sets(layout)
limits = InputLimits()


def run(light_after: int, new_every: float) -> tuple[float, list[list[tuple[int, ...]]]]:
    """ms CPU per set after WARM, and each set's clusters as the persons of their members."""
    stage = TemporalAssociator(
        rig, AssociationParams.from_mapping(p), TemporalParams.from_mapping({**p, "light_new_every": new_every})
    )
    cpu, found = 0.0, []
    for f, frame_set in enumerate(msgs):
        stamp, light = int(f * 1e9 / 60), f >= light_after
        t0 = time.process_time()
        read = {c: checked_detections(m, "/t", c, rig, limits, stage.gates) for c, m in frame_set}
        vertices = stage.associates_new(stamp, light)
        items = {c: prepared_detections(m, stage.gates, vertices) for c, m in read.items()}
        res = stage.step(items, stamp, light)
        cpu += time.process_time() - t0 if f >= WARM else 0.0
        who = {c: scene.detection_persons(c, f) for c in rig.names}
        found.append([tuple(who[rig.names[c]][d] for c, d in cl.members.tolist()) for cl in res.clusters])
    return cpu / (len(msgs) - WARM) * 1e3, found[WARM:]


run(WARM, 0.0)  # compile the keypoint epipolar kernel the light step uses
for name, light_after, every in (("full", len(msgs), 0.1), ("light, new every set", WARM, 0.0),
                                 ("light, new every 0.1 s", WARM, 0.1)):
    ms, found = run(light_after, every)
    clusters = [cl for sets in found for cl in sets]
    mixed = sum(len({q for q in cl if q >= 0}) > 1 for cl in clusters)
    print(f"{layout} {name}: {ms:.2f} ms CPU per set, {len(clusters)} clusters, {mixed} mixing people, "
          f"{sum(len(cl) for cl in clusters)} member views")
