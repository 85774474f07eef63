"""The wire: core <-> message layouts, the one place that knows them (doc/design.md §4). No rclpy.

PointCloud2 layouts (one point per row, little-endian, packed, height 1):

* detections (``/<cam>/detections``), one point per detection, all float32:
  ``bbox``(4: x1 y1 x2 y2 rectified px) ``score``(1) ``kpts2d``(2J rectified px, u v per joint,
  NaN = keypoint not seen, e.g. under the frontend's visibility threshold)
  ``kpts3d``(3J m, camera-relative) ``verts2d``(2V rectified px). header.frame_id = camera name,
  header.stamp = image capture stamp. J and V come from the counts.
  Compact variant (:data:`WIRE_VERTICES` ``q4``): ``verts2d_q4`` (uint16 x 2V) instead of
  ``verts2d``, value = round((px - origin) * 16) (1/16 px steps over 4095.875 px from the origin),
  65535 = missing (outside that range); ``verts2d_q4_origin`` (f32 x 2, optional, default 0 0)
  is the detection's origin in px: the encoder puts it at the floor of the detection's smallest
  vertex coordinates, so people whose rectified vertices are negative or beyond 4096 px (wide,
  strongly distorted cameras) lose nothing; optionally ``kpts2d_q4`` (uint16 x 2J, 65535 = not seen) instead
  of ``kpts2d``. A vertex subset is announced by ``verts2d_subset`` (uint32 x 3: full mesh
  vertices, stride, count; core.detections.vertex_subset gives the ids) in every point.
* clusters (``/maem/clusters``), one point per (cluster, member view): ``cluster``(uint32, index in
  the frame) ``camera``(uint16, index in the rig's camera order) ``detection``(uint16, index in
  that camera's detections message) ``score``(f32) ``cost``(f32, mean PA-MPJPE m to the rest of
  the cluster, NaN if alone) ``kpts2d``(f32 x 2J rectified px). header.stamp = frame-set stamp.
  With temporal association also ``track``(uint32 track id, 4294967295 = tentative) and
  ``track_flags``(uint8, core.tracking.temporal FLAG_* bits: 1 tracked, 2 fewer than k_min views).
* poses (``/maem/poses``), one point per person: ``id``(uint32 track id, 4294967295 = not yet
  confirmed) ``joints``(f32 x 3J world m, NaN = missing) ``views``(uint16) ``score``(f32, see
  core/triangulation/uncertainty.py), optionally ``joint_std``(f32 x J, per-joint standard
  deviation in m, NaN where the joint is missing; decoders that read fields by name ignore it).

Decoders build one numpy structured dtype from msg.fields and view msg.data with np.frombuffer
(no copy of the payload). Any problem raises :class:`WireError` (a ValueError) naming topic,
field and problem, with a short ``reason`` code for /diagnostics.

Modules: cloud (PointCloud2 <-> structured arrays, stamps, WireError), cdr (CDR bytes via the
rosbags typestore, rosbags messages), detections (incl. q4), clusters, poses, markers (what the
skeleton markers hold), images, tf. Encoders build a :class:`~maem_ros.wire.cloud.Cloud`
(``*_to_cloud``) or a rosbags message for a bag writer (``*_to_msg``); ros/wire turns the same
clouds into rclpy messages for the nodes. Offline tools read bags with this package alone.
"""

from maem_ros.wire.cdr import cdr_header_stamp_ns, cdr_to_cloud, make_header, ns_to_stamp, to_rosbags
from maem_ros.wire.cloud import (
    F32,
    MAX_STAMP_NS,
    U8,
    U16,
    U32,
    Cloud,
    WireError,
    checked_stamp_ns,
    new_cloud,
    stamp_to_ns,
)
from maem_ros.wire.clusters import (
    CLUSTER_TRACK_TYPES,
    CLUSTER_TYPES,
    ClusterFrame,
    clusters_to_cloud,
    clusters_to_msg,
    msg_to_clusters,
)
from maem_ros.wire.detections import (
    DETECTION_TYPES,
    ORIGIN_FIELD,
    Q4_FIELDS,
    Q4_MISSING,
    Q4_SCALE,
    SUBSET_FIELD,
    WIRE_VERTICES,
    DetectionsMessage,
    decode_q4,
    detections_to_cloud,
    detections_to_msg,
    encode_q4,
    msg_to_detections,
    q4_origin,
    read_detections,
)
from maem_ros.wire.images import (
    JPEG_FORMAT,
    bgr_to_compressed,
    camera_info_msg,
    compressed_image_msg,
    compressed_to_bgr,
    encode_jpeg,
    image_to_bgr,
)
from maem_ros.wire.markers import NS_BONES, NS_DELETE_ALL, NS_JOINTS, NS_LABELS, SkeletonPlan, skeleton_plan
from maem_ros.wire.poses import (
    POSE_OPTIONAL,
    POSE_TYPES,
    UNTRACKED_ID,
    PoseFrame,
    msg_to_poses,
    poses_to_cloud,
    poses_to_msg,
)
from maem_ros.wire.tf import TF_MESSAGE, TF_STATIC_TOPIC, msg_to_transforms, tf_message

__all__ = [
    "CLUSTER_TRACK_TYPES",
    "CLUSTER_TYPES",
    "DETECTION_TYPES",
    "F32",
    "JPEG_FORMAT",
    "MAX_STAMP_NS",
    "NS_BONES",
    "NS_DELETE_ALL",
    "NS_JOINTS",
    "NS_LABELS",
    "ORIGIN_FIELD",
    "POSE_OPTIONAL",
    "POSE_TYPES",
    "Q4_FIELDS",
    "Q4_MISSING",
    "Q4_SCALE",
    "SUBSET_FIELD",
    "TF_MESSAGE",
    "TF_STATIC_TOPIC",
    "U16",
    "U32",
    "U8",
    "UNTRACKED_ID",
    "WIRE_VERTICES",
    "Cloud",
    "ClusterFrame",
    "DetectionsMessage",
    "PoseFrame",
    "SkeletonPlan",
    "WireError",
    "bgr_to_compressed",
    "camera_info_msg",
    "cdr_header_stamp_ns",
    "cdr_to_cloud",
    "checked_stamp_ns",
    "clusters_to_cloud",
    "clusters_to_msg",
    "compressed_image_msg",
    "compressed_to_bgr",
    "decode_q4",
    "detections_to_cloud",
    "detections_to_msg",
    "encode_jpeg",
    "encode_q4",
    "image_to_bgr",
    "make_header",
    "msg_to_clusters",
    "msg_to_detections",
    "msg_to_poses",
    "msg_to_transforms",
    "new_cloud",
    "ns_to_stamp",
    "poses_to_cloud",
    "poses_to_msg",
    "q4_origin",
    "read_detections",
    "skeleton_plan",
    "stamp_to_ns",
    "tf_message",
    "to_rosbags",
]
