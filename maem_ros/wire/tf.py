"""TF (tf2_msgs/TFMessage) <-> core.geometry.frames transforms; rosbags message classes by
default, any others (rclpy's, from ros/wire) on request. No rclpy."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.core.geometry.frames import FrameTransform
from maem_ros.wire.cloud import WireError

#: topic of the rig's static transforms (ROS convention: global, transient local)
TF_STATIC_TOPIC = "/tf_static"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def tf_message(transforms: Sequence[FrameTransform], stamp_ns: int, types: Any = None) -> Any:
    """tf2_msgs/TFMessage of core.geometry.frames transforms (one TransformStamped each,
    header.stamp = ``stamp_ns``). ``types``: msgtype -> class, a mapping (default the rosbags
    typestore's ``types``, for a bag writer) or a callable (ros/wire passes rclpy's)."""
    src = bagio.TYPESTORE.types if types is None else types
    T: Callable[[str], Any] = src if callable(src) else src.__getitem__
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    Time_, Header_ = T("builtin_interfaces/msg/Time"), T("std_msgs/msg/Header")
    Vector3, Quaternion = T("geometry_msgs/msg/Vector3"), T("geometry_msgs/msg/Quaternion")
    Transform, Stamped = T("geometry_msgs/msg/Transform"), T("geometry_msgs/msg/TransformStamped")
    out = []
    for tr in transforms:
        x, y, z = (float(v) for v in tr.translation)
        qx, qy, qz, qw = (float(v) for v in tr.quaternion)
        out.append(
            Stamped(
                header=Header_(stamp=Time_(sec=sec, nanosec=nsec), frame_id=tr.parent),
                child_frame_id=tr.child,
                transform=Transform(
                    translation=Vector3(x=x, y=y, z=z), rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)
                ),
            )
        )
    return T(TF_MESSAGE)(transforms=out)


def msg_to_transforms(msg: Any, topic: str) -> list[FrameTransform]:
    """TFMessage (rclpy or rosbags) -> core.geometry.frames transforms; WireError on a
    non-unit quaternion or a non-finite value."""
    out = []
    for i, ts in enumerate(msg.transforms):
        t, r = ts.transform.translation, ts.transform.rotation
        tr = np.array([t.x, t.y, t.z], dtype=np.float64)
        q = np.array([r.x, r.y, r.z, r.w], dtype=np.float64)
        if not (np.isfinite(tr).all() and np.isfinite(q).all()) or abs(np.linalg.norm(q) - 1) > 1e-6:
            raise WireError(
                topic,
                f"transforms[{i}]",
                f"non-finite value or non-unit quaternion {q.tolist()}",
                "bad_transform",
            )
        out.append(FrameTransform(ts.header.frame_id, ts.child_frame_id, tr, q))
    return out
