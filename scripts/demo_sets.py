"""The live benchmark's frame sets, offline, for the timing scripts next to this one: the
config/demo.yaml scene (6 cameras), the association node's parameters for it, its rig, and
each frame's detections messages in the given wire layout (f32 full mesh or q4)."""

from typing import Any

from maem_ros.params import load_node_params
from maem_ros.ros import wire
from maem_ros.ros.association_node import PARAMS
from maem_ros.ros.params import load_rig_param
from maem_ros.tools.bench.latency import make_scene
from maem_ros.tools.bench.live import _encode


def demo_sets(layout: str, frames: int | None = None) -> tuple[Any, dict, Any, list[list[tuple[str, Any]]]]:
    """(scene, association parameters, rig, per frame [(camera, PointCloud2)]) of the first
    ``frames`` frames (None: all)."""
    scene = make_scene("demo.yaml")
    p = {s.name: s.default for s in PARAMS}
    p.update(load_node_params("demo.yaml", "association"))
    rig = load_rig_param(p.get("rig", ""))
    count = scene.num_frames if frames is None else min(frames, scene.num_frames)
    msgs = [
        [(c, wire.cdr_to_cloud(_encode(scene.detections(c, f), layout, 1), "/t")) for c in rig.names]
        for f in range(count)
    ]
    return scene, p, rig, msgs
