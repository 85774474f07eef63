"""rclpy PointCloud2 and stamps from the codec's clouds (maem_ros.wire)."""

from __future__ import annotations

import array
from collections.abc import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from maem_ros import wire as codec
from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Rig


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds (0 .. MAX_STAMP_NS) -> builtin_interfaces/Time; ValueError outside."""
    sec, nsec = codec.cloud.split_stamp(ns)
    return Time(sec=sec, nanosec=nsec)


def make_header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def cloud_to_msg(cloud: codec.Cloud) -> PointCloud2:
    """A codec Cloud -> rclpy PointCloud2; the cloud's buffer becomes msg.data (an array.array
    'B', which the generated setter takes as it is: one memcpy at most)."""
    h = cloud.header
    msg = PointCloud2(
        header=Header(stamp=Time(sec=h.stamp.sec, nanosec=h.stamp.nanosec), frame_id=h.frame_id),
        height=cloud.height,
        width=cloud.width,
        is_bigendian=cloud.is_bigendian,
        point_step=cloud.point_step,
        row_step=cloud.row_step,
        is_dense=cloud.is_dense,
    )
    msg.fields = [
        PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in cloud.fields
    ]
    data = cloud.data
    msg.data = data if isinstance(data, array.array) else array.array("B", bytes(data))
    return msg


def detections_to_msg(dets: FrameDetections, vertices: str = "f32", keypoints: str = "f32") -> PointCloud2:
    """FrameDetections -> PointCloud2 (see maem_ros.wire.detections.detections_to_cloud)."""
    return cloud_to_msg(codec.detections_to_cloud(dets, vertices, keypoints))


def clusters_to_msg(
    stamp_ns: int,
    frame_id: str,
    rig: Rig,
    frames: Mapping[str, FrameDetections],
    clusters: Sequence,
    track_ids: Sequence[int] | np.ndarray | None = None,
    track_flags: Sequence[int] | np.ndarray | None = None,
) -> PointCloud2:
    """core Clusters -> PointCloud2 (see maem_ros.wire.clusters.clusters_to_cloud)."""
    return cloud_to_msg(
        codec.clusters_to_cloud(stamp_ns, frame_id, rig, frames, clusters, track_ids, track_flags)
    )


def poses_to_msg(
    stamp_ns: int,
    frame_id: str,
    ids: np.ndarray,
    joints: np.ndarray,
    views: np.ndarray,
    scores: np.ndarray,
    joint_std: np.ndarray | None = None,
) -> PointCloud2:
    """Persons -> PointCloud2 (see maem_ros.wire.poses.poses_to_cloud)."""
    return cloud_to_msg(codec.poses_to_cloud(stamp_ns, frame_id, ids, joints, views, scores, joint_std))


def warm_cdr_decoder() -> None:
    """Build the PointCloud2 decoder cdr_to_cloud uses now (rosbags generates and compiles it
    on first use), so the first frame after start-up does not pay for it."""
    from rclpy.serialization import serialize_message

    codec.cdr_to_cloud(bytes(serialize_message(PointCloud2())), "warm-up")
