"""rclpy skeleton MarkerArray from the codec's plan (maem_ros.wire.markers)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from maem_ros.core.colors import id_rgb
from maem_ros.ros.wire.clouds import make_header
from maem_ros.wire.markers import NS_BONES, NS_DELETE_ALL, NS_JOINTS, NS_LABELS, skeleton_plan


def id_color(track_id: int, alpha: float = 1.0) -> ColorRGBA:
    """The id's colour (core.colors.id_rgb) as std_msgs/ColorRGBA."""
    r, g, b = id_rgb(track_id)
    return ColorRGBA(r=r, g=g, b=b, a=float(alpha))


def skeleton_markers(
    stamp_ns: int,
    frame_id: str,
    ids: Sequence[int] | np.ndarray,
    joints: np.ndarray,
    bones: Sequence[tuple[int, int]],
    lifetime_s: float = 0.5,
    joint_diameter: float = 0.06,
    bone_width: float = 0.03,
) -> MarkerArray:
    """Per person: SPHERE_LIST joints (ns skeleton/joints), LINE_LIST bones (ns skeleton/bones,
    bones with a NaN end skipped), TEXT_VIEW_FACING id 0.3 m above the highest joint
    (ns skeleton/ids). Marker id = track id in each ns; persons with id < 0 or no finite joint
    are skipped. The array starts with a DELETEALL marker (ns NS_DELETE_ALL), so each frame
    replaces the previous one whatever the replay rate; markers also expire after
    ``lifetime_s`` (> 0) so the view empties when the stream stops.
    """
    header = make_header(stamp_ns, frame_id)
    sec, nsec = divmod(int(round(lifetime_s * 1e9)), 1_000_000_000)
    life = Duration(sec=sec, nanosec=nsec)
    out = MarkerArray(markers=[Marker(header=header, ns=NS_DELETE_ALL, id=0, action=Marker.DELETEALL)])
    if len(ids) == 0:
        return out
    plan = skeleton_plan(ids, joints, bones)
    points = [Point(x=x, y=y, z=z) for x, y, z in plan.points.tolist()]
    first = plan.first.tolist()
    for k, mid in enumerate(plan.ids):
        color = id_color(mid)
        joint_m = Marker(
            header=header,
            ns=NS_JOINTS,
            id=mid,
            type=Marker.SPHERE_LIST,
            action=Marker.ADD,
            lifetime=life,
            color=color,
            points=points[first[k] : first[k + 1]],
        )
        joint_m.pose.orientation.w = 1.0
        joint_m.scale.x = joint_m.scale.y = joint_m.scale.z = joint_diameter
        bone_m = Marker(
            header=header,
            ns=NS_BONES,
            id=mid,
            type=Marker.LINE_LIST,
            action=Marker.ADD,
            lifetime=life,
            color=color,
            points=[points[i] for i in plan.bones[k]],
        )
        bone_m.pose.orientation.w = 1.0
        bone_m.scale.x = bone_width
        text_m = Marker(
            header=header,
            ns=NS_LABELS,
            id=mid,
            type=Marker.TEXT_VIEW_FACING,
            action=Marker.ADD,
            lifetime=life,
            text=str(mid),
            color=color,
        )
        x, y, z = plan.labels[k].tolist()
        text_m.pose.position = Point(x=x, y=y, z=z)
        text_m.pose.orientation.w = 1.0
        text_m.scale.z = 0.25
        out.markers.extend([joint_m, bone_m, text_m])
    return out
