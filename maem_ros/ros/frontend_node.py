"""Frontend node: one camera's images -> /<camera>/detections (PointCloud2, one point per detection).

Run one per camera, in the camera's namespace::

    ros2 run maem_ros frontend --ros-args --params-file config/demo.yaml -r __ns:=/camera_0
    maem-frontend --ros-args -p rig:=sportcenter6 -p backend:=synthetic -r __ns:=/camera_0

Subscribes ``image_raw`` (sensor_msgs/Image) or ``image_raw/compressed`` (CompressedImage), best
effort (``image_reliability: reliable`` for a replay that must not lose an image); publishes
``detections`` (reliable, keep last 10) stamped with the image stamp, and with ``publish_overlay``
``detections/overlay`` (Image bgr8, the rectified image with the detections).
The image is decoded (and rectified) only when the backend or the overlay needs it.
``max_rate`` decimates on the stamp grid (one image per 1/max_rate s interval of the stamp), so
frontends that cannot keep up with the cameras all keep the same instants and the association
still finds complete frame sets (dropping by queue overflow would keep different frames per
camera).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

from sensor_msgs.msg import CompressedImage, Image, PointCloud2

from maem_ros.core.paramspec import param
from maem_ros.ros import wire
from maem_ros.ros.diagnostics import RejectErrors, Stopwatch
from maem_ros.ros.intake import subscribe_counted
from maem_ros.ros.node import MaemNode
from maem_ros.ros.params import (
    ConfigError,
    NodeParams,
    default_camera_name,
)
from maem_ros.ros.qos import DATA_QOS, IMAGE_QOS, RELIABLE_IMAGE_QOS

NODE_NAME = "frontend"


@dataclass
class FrontendNodeParams(NodeParams):
    """The frontend node's parameters (estimator backends' options included)."""

    camera: str = param("", "camera name = rig key = frame_id (default: last namespace component)")
    rig: str = param("", "rig YAML, camera-JSON folder or shipped rig name (config/rigs/)")
    backend: str = param(
        "synthetic", "estimator backend", choices=("synthetic", "npz", "sam3d_body", "mediapipe")
    )
    image_transport: str = param(
        "raw", "subscribe image_raw (raw) or image_raw/compressed", choices=("raw", "compressed")
    )
    image_reliability: str = param(
        "best_effort",
        "image subscription QoS: best_effort (sensor "
        "data, matches every camera driver) or reliable "
        "(keep last 10: no image lost from a reliable "
        "publisher, e.g. maem-play --reliable-images)",
        choices=("best_effort", "reliable"),
    )
    publish_overlay: bool = param(False, "also publish detections/overlay (rectified image + drawing)")
    vertex_stride: int = param(1, "keep every n-th mesh vertex in verts2d (announced on the wire)", minimum=1)
    vertex_count: int = param(
        0,
        "then keep this many of them, spread over the mesh (0 = all; "
        "core.association.gates.epipolar.vertex_subset, announced on the "
        "wire)",
        minimum=0,
    )
    wire_vertices: str = param(
        "f32", "verts2d layout: f32, or q4 (uint16, 1/16 px, half the bytes)", choices=("f32", "q4")
    )
    wire_keypoints: str = param("f32", "kpts2d layout: f32 or q4", choices=("f32", "q4"))
    max_rate: float = param(
        0.0,
        "Hz, process at most one image per 1/max_rate stamp interval "
        "(stamp-aligned, so every camera keeps the same frames); "
        "0 = every image",
        minimum=0.0,
    )
    # synthetic backend (sentinels -1 / 0 / '' = the scene's default)
    scene_dict: str = param("", "synthetic: SceneConfig as JSON (as recorded in bags)")
    scene_rig: str = param("", "synthetic: sim rig name (default: the rig parameter)")
    seed: int = param(-1, "synthetic: scene seed (-1 = scene default)", minimum=-1)
    difficulty: str = param(
        "", "synthetic: detection noise level", choices=("", "none", "easy", "medium", "hard")
    )
    frames: int = param(0, "synthetic: scene length in frames (0 = scene default)", minimum=0)
    num_vertices: int = param(0, "synthetic: mesh vertices per person (0 = scene default)", minimum=0)
    # synthetic and npz
    fps: float = param(0.0, "frame rate, Hz (0 = scene / scene.json default)", minimum=0.0)
    start_stamp_ns: int = param(-1, "stamp of frame 0, ns (-1 = scene / scene.json default)", minimum=-1)
    # npz backend
    dets_dir: str = param("", "npz: folder with <camera>/<frame>.npz (or a scene folder)")
    # sam3d_body backend (frontend/sam3d_body.py; '' = the backend's default)
    checkpoint_path: str = param("", "sam3d_body: model.ckpt of the official SAM 3D Body weights")
    mhr_path: str = param("", "sam3d_body: MHR model (default: assets/mhr_model.pt beside the checkpoint)")
    hf_repo_id: str = param("", "sam3d_body: load from a local Hugging Face cache instead")
    repo_path: str = param("", "sam3d_body: clone of facebookresearch/sam-3d-body, if not installed")
    device: str = param("auto", "sam3d_body: auto | cpu | cuda | cuda:N")
    precision: str = param("fp32", "sam3d_body: inference precision", choices=("fp32", "fp16", "bf16"))
    detector: str = param("vitdet", "sam3d_body: person detector", choices=("vitdet", "model", "none"))
    bbox_thr: float = param(0.5, "sam3d_body: detector score threshold", minimum=0.0)
    inference_type: str = param("full", "sam3d_body: full (body + hands) or body", choices=("full", "body"))
    keypoint_convention: str = param(
        "",
        "sam3d_body / mediapipe: keypoints published ('' = the backend's own: mhr70 / blazepose_33)",
        choices=("", "mhr70", "sportcenter_13", "coco_17", "blazepose_33"),
    )
    # mediapipe backend (frontend/mediapipe_pose.py)
    max_people: int = param(4, "mediapipe: people searched per image (one model pass each)", minimum=1)
    min_detection_confidence: float = param(
        0.5, "mediapipe: BlazePose detector threshold", minimum=0.0, maximum=1.0
    )
    min_bbox_height: float = param(0.0, "mediapipe: px, smaller people are dropped", minimum=0.0)
    mask_threshold: float = param(
        0.5, "mediapipe: segmentation probability of the person", minimum=0.0, maximum=1.0
    )
    mask_dilate: int = param(15, "mediapipe: px grown around a found person before masking it", minimum=0)
    duplicate_overlap: float = param(
        0.6,
        "mediapipe: landmark fraction inside earlier people's masks that makes a detection a duplicate",
        minimum=0.0,
        maximum=1.0,
    )
    pnp_min_visibility: float = param(
        0.5,
        "mediapipe: landmark visibility used to place the 3D pose in the camera",
        minimum=0.0,
        maximum=1.0,
    )
    min_visibility: float = param(
        0.0, "mediapipe: landmarks under this visibility are sent as NaN (not seen)", minimum=0.0, maximum=1.0
    )


PARAMS = FrontendNodeParams.specs()

SAM3D_KEYS = (
    "checkpoint_path",
    "mhr_path",
    "hf_repo_id",
    "repo_path",
    "device",
    "precision",
    "detector",
    "bbox_thr",
    "inference_type",
    "keypoint_convention",
)
MEDIAPIPE_KEYS = (
    "keypoint_convention",
    "max_people",
    "min_detection_confidence",
    "min_bbox_height",
    "mask_threshold",
    "mask_dilate",
    "duplicate_overlap",
    "pnp_min_visibility",
    "min_visibility",
)


def backend_options(p: dict[str, Any]) -> dict[str, Any]:
    """Estimator options from the node parameters (sentinel values left out)."""
    opts: dict[str, Any] = {"vertex_stride": p["vertex_stride"]}
    if p["scene_dict"]:
        opts["scene_dict"] = p["scene_dict"]
    opts["rig"] = p["scene_rig"] or p["rig"]
    for key, unset in (
        ("seed", -1),
        ("difficulty", ""),
        ("frames", 0),
        ("num_vertices", 0),
        ("fps", 0.0),
        ("start_stamp_ns", -1),
        ("dets_dir", ""),
    ):
        if p[key] != unset:
            opts[key] = p[key]
    if p["backend"] != "synthetic":
        opts.pop("rig")
    if p["backend"] == "sam3d_body":
        opts.update({key: p[key] for key in SAM3D_KEYS})
    if p["backend"] == "mediapipe":
        opts.update({key: p[key] for key in MEDIAPIPE_KEYS})
    return opts


#: heap touched at start (MiB): the detections message being encoded and published (~1.8 MB
#: per copy with the full mesh)
HEAP_PREFAULT_MB = 64


class FrontendNode(MaemNode):
    """image -> estimator backend -> detections, for one camera."""

    NAME, PARAMS, HEAP_PREFAULT_MB = NODE_NAME, PARAMS, HEAP_PREFAULT_MB

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        p = self.p
        self.camera_name = p["camera"] or default_camera_name(self)
        if not self.camera_name:
            raise ConfigError(
                "parameter 'camera': empty and the node runs in the root namespace; "
                "set camera:=<name> or -r __ns:=/<camera>"
            )
        rig = self.load_rig()
        if self.camera_name not in rig:
            raise ConfigError(
                f"parameter 'camera': {self.camera_name!r} is not in rig {p['rig']!r} ({rig.names})"
            )
        self.camera = rig[self.camera_name]
        from maem_ros.frontend.base import make_estimator

        try:
            self.estimator = make_estimator(p["backend"], backend_options(p), rig)
        except (ValueError, ImportError) as e:
            raise ConfigError(f"backend {p['backend']!r}: {e}") from None
        self.publish_overlay = p["publish_overlay"]
        self.vertex_stride, self.vertex_count = p["vertex_stride"], p["vertex_count"]
        self.wire_vertices, self.wire_keypoints = p["wire_vertices"], p["wire_keypoints"]
        self._bucket_ns = int(round(1e9 / p["max_rate"])) if p["max_rate"] > 0 else 0
        self._last_bucket: int | None = None
        self._rectifier = None
        if self.estimator.needs_image or self.publish_overlay:
            from maem_ros.frontend.rectify import Rectifier

            self._rectifier = Rectifier(self.camera)
        prefix = "" if default_camera_name(self) == self.camera_name else f"{self.camera_name}/"
        self.start_diagnostics(hardware_id=self.camera_name)
        self.diag.set("backend", p["backend"])
        self.pub = self.create_publisher(PointCloud2, f"{prefix}detections", DATA_QOS)
        self.overlay_pub = (
            self.create_publisher(Image, f"{prefix}detections/overlay", RELIABLE_IMAGE_QOS)
            if self.publish_overlay
            else None
        )
        compressed = p["image_transport"] == "compressed"
        self.image_topic = self.resolve_topic_name(
            f"{prefix}image_raw/compressed" if compressed else f"{prefix}image_raw"
        )
        qos = IMAGE_QOS if p["image_reliability"] == "best_effort" else RELIABLE_IMAGE_QOS
        self.sub = subscribe_counted(
            self, self.diag, CompressedImage if compressed else Image, self.image_topic, self.on_image, qos
        )
        self.get_logger().info(
            f"camera {self.camera_name!r}: {self.image_topic} -> "
            f"{self.pub.topic_name} (backend {p['backend']})"
        )

    def _decode(self, msg) -> Any:
        if isinstance(msg, CompressedImage):
            return wire.compressed_to_bgr(msg, self.image_topic)
        return wire.image_to_bgr(msg, self.image_topic)

    def skip(self, stamp_ns: int) -> bool:
        """True when ``max_rate`` says this stamp's interval already had its image."""
        if not self._bucket_ns:
            return False
        bucket = stamp_ns // self._bucket_ns
        if bucket == self._last_bucket:
            return True
        self._last_bucket = bucket
        return False

    def on_image(self, msg) -> None:
        try:
            stamp_ns = wire.checked_stamp_ns(msg.header.stamp, self.image_topic)
        except wire.WireError as e:
            self.diag.reject(e.reason, str(e))
            return
        if self.skip(stamp_ns):
            self.diag.count("skipped_max_rate")
            return
        with RejectErrors(self.diag, self.image_topic, "estimator") as step:
            with Stopwatch(self.diag, "total"):
                rect = None
                if self._rectifier is not None:
                    with Stopwatch(self.diag, "decode"):
                        rect = self._rectifier.rectify(self._decode(msg))
                with Stopwatch(self.diag, "estimate"):
                    dets = self.estimator.estimate(
                        self.camera, stamp_ns, rect if self.estimator.needs_image else None
                    )
                with Stopwatch(self.diag, "encode"):
                    if self.vertex_count:
                        dets = dets.with_vertex_subset(self.vertex_stride, self.vertex_count)
                    out = wire.detections_to_msg(dets, self.wire_vertices, self.wire_keypoints)
                self.pub.publish(out)
                if self.overlay_pub is not None:
                    self._publish_overlay(rect, dets, stamp_ns)
        if step.failed:
            return
        self.diag.ok()
        self.diag.set("last_detections", dets.n)

    def _publish_overlay(self, rect, dets, stamp_ns: int) -> None:
        from maem_ros.frontend.overlay import draw_detections

        assert self.overlay_pub is not None  # called only with publish_overlay
        with Stopwatch(self.diag, "overlay"):
            self.overlay_pub.publish(
                wire.bgr_to_image(draw_detections(rect, dets), stamp_ns, self.camera_name)
            )


def main(args: list[str] | None = None) -> int:
    return FrontendNode.main(args)


if __name__ == "__main__":
    sys.exit(main())
