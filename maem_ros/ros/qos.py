"""QoS profiles of the node graph (chosen deliberately, see doc/design.md §4).

* images: sensor data (best effort, keep last 2): a slow frontend drops stale frames instead of
  queueing them, and best-effort subscribers also accept reliable camera drivers.
* detections / clusters / poses: reliable, keep last DATA_DEPTH, volatile: every processed
  frame reaches the next stage while a burst is buffered; no history for late joiners.
* markers: reliable, keep last 10 (RViz default subscription QoS).
* /diagnostics: reliable, keep last 10 (what diagnostic_aggregator expects).
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

#: camera images: best effort, keep last 2
IMAGE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=2,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)
#: images from a replay that must arrive (maem-play --reliable-images): reliable, keep last 10
RELIABLE_IMAGE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
#: messages kept per per-frame stream (detections, clusters, poses) at both ends, writer and
#: reader: ~1 s at 30 fps, so a node starved of CPU for a while (a few hundred ms happen on a
#: loaded machine) finds every message of the stall still queued instead of overwritten
#: (dropped/dds_lost),
#: and the upstream node's backlog, sent as a burst afterwards, fits
DATA_DEPTH = 32


def data_qos(depth: int = DATA_DEPTH) -> QoSProfile:
    """Per-frame streams: reliable, keep last ``depth``, volatile."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


DATA_QOS = data_qos()
#: MarkerArray for RViz: reliable, keep last 10
MARKER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
#: /tf_static: reliable, transient local, keep last 1 (what tf2's static broadcaster offers)
TF_STATIC_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
#: /diagnostics: reliable, keep last 10
DIAGNOSTICS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
