"""The association node's work per frame set before it associates: every camera's message
checked (fields, limits), decoded and prepared for the pair gates (as the node does it:
ros.association_node.checked_detections and prepared_detections), on the maem-bench standard
load (6 cameras x 12 detections, full mesh). Runs on this tree and on the pre-renovation tree
(7768492, where wire decoded and screened in one call), to compare them in the same session:

    python scripts/node_path_time.py f32|q4
    (cd OLD_WORKTREE && PYTHONPATH=. python /path/to/scripts/node_path_time.py f32|q4)
"""

import sys
import time

import numpy as np

from maem_ros.core.association import AssociationParams
from maem_ros.params import load_node_params
from maem_ros.ros import wire

try:
    from maem_ros.core.synthetic import body_template, make_frame
    from maem_ros.tools.bench.bench_load import load_bench_rig

    NEW = True
except ImportError:
    from maem_ros.tools.bench_load import body_template, load_bench_rig, make_frame

    NEW = False
from maem_ros.core.limits import InputLimits

rig = load_bench_rig("sportcenter6")
ap = AssociationParams.from_mapping({**load_node_params("sportcenter.yaml", "association")})
fr = make_frame(rig, body_template(18439, 70, 0), np.random.default_rng(0), 10, 2, stamp_ns=0)
msgs = {c: wire.detections_to_msg(fd, sys.argv[1]) for c, fd in fr.frames.items()}
limits = InputLimits()
if NEW:
    from maem_ros.core.association import PairGates
    from maem_ros.ros.association_node import checked_detections, prepared_detections

    gates = PairGates(rig, ap)

    def one_set():
        got = {c: checked_detections(m, f"/{c}/detections", c, rig, limits, gates) for c, m in msgs.items()}
        return {c: prepared_detections(item, gates) for c, item in got.items()}
else:
    from maem_ros.core.association import decode_screen_strides
    from maem_ros.core.limits import check_detections

    scr = decode_screen_strides(ap)

    def one_set():
        out = {}
        for c, m in msgs.items():
            d = wire.msg_to_detections(
                m, f"/{c}/detections", rig.names, expected_camera=c, screen_strides=scr
            )
            check_detections(d, rig, limits, "/t")
            out[c] = d
        return out


for _ in range(20):
    one_set()
ts = []
for _ in range(400):
    t = time.perf_counter()
    one_set()
    ts.append(time.perf_counter() - t)
print(("new" if NEW else "old"), sys.argv[1], "node path ms/set median %.3f" % (np.median(ts) * 1e3))
