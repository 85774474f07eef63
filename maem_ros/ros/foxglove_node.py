"""Foxglove node: the live graph in Foxglove over a WebSocket (foxglove-sdk), no ROS install in
the viewer and no foxglove_bridge needed.

    ros2 run maem_ros foxglove --ros-args -p rig:=sportcenter6
    maem-foxglove --ros-args --params-file config/demo.yaml

Subscribes ``poses_topic`` (maem/poses, reliable) and per camera of the rig (``cameras``, default
all) <cam>/image_raw/compressed (``image_transport: compressed``) or <cam>/image_raw (raw,
JPEG-encoded for Foxglove) and <cam>/camera_info (best effort, accepts either publisher); the
names are relative, so in the root namespace they are /maem/poses, /<cam>/..., and under
``-r __ns:=/team`` /team/maem/poses, /team/<cam>/... Serves
on ``host``:``port`` (default 127.0.0.1:8765) the channels of maem_ros/viz/bridge.py: 3D
skeletons, court and camera frustums, world -> camera transforms, images, calibrations and the
skeletons reprojected into every image. A message that cannot be decoded is dropped with its
reason in /diagnostics; the node keeps running. For a bag without a ROS graph:
``maem-foxglove --bag BAG``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2

from maem_ros.core.paramspec import param, param_specs
from maem_ros.core.skeleton import CONVENTIONS
from maem_ros.ros import wire
from maem_ros.ros.diagnostics import RejectErrors, Stopwatch
from maem_ros.ros.node import MaemNode
from maem_ros.ros.params import ConfigError, NodeParams
from maem_ros.ros.qos import DATA_QOS, IMAGE_QOS
from maem_ros.viz.scene import camera_info_fields

NODE_NAME = "foxglove"


@dataclass
class FoxgloveNodeParams(NodeParams):
    """The Foxglove node's parameters."""

    rig: str = param("", "rig YAML, camera-JSON folder or shipped rig name (config/rigs/)")
    cameras: list = param([], "cameras to show (default: every camera of the rig)")
    poses_topic: str = param(
        "maem/poses", "input topic (PointCloud2, poses layout; relative names follow the node's namespace)"
    )
    image_transport: str = param("compressed", "camera images to subscribe", choices=("compressed", "raw"))
    convention: str = param(
        "",
        "keypoint convention of the poses (empty: from the joint count)",
        choices=("",) + tuple(sorted(CONVENTIONS)),
    )
    frame_id: str = param(
        "world", "the rig's world frame (triangulation's frame_id): parent of the camera transforms"
    )
    host: str = param("127.0.0.1", "address the Foxglove WebSocket server listens on")
    port: int = param(8765, "WebSocket port (0 = a free port, logged)", minimum=0, maximum=65535)
    court_length: float = param(28.0, "m, court floor length (x)", minimum=0.0, exclusive_minimum=True)
    court_width: float = param(15.0, "m, court floor width (y)", minimum=0.0, exclusive_minimum=True)
    static_period: float = param(
        1.0,
        "s, period of resending court, frustums, transforms and calibrations",
        minimum=0.0,
        exclusive_minimum=True,
    )


PARAMS = param_specs(FoxgloveNodeParams)


class FoxgloveNode(MaemNode):
    """poses + images + camera_info -> FoxgloveBridge."""

    NAME, PARAMS = NODE_NAME, PARAMS

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        p = self.p
        rig = self.load_rig()
        if p["cameras"]:
            unknown = [c for c in p["cameras"] if c not in rig]
            if unknown:
                raise ConfigError(f"parameter 'cameras': {unknown} not in the rig ({rig.names})")
            from maem_ros.core.geometry.camera import Rig

            rig = Rig([rig[c] for c in p["cameras"]])
        from maem_ros.viz.bridge import FoxgloveBridge

        try:
            self.bridge = FoxgloveBridge(
                rig,
                host=p["host"],
                port=p["port"],
                court_size=(p["court_length"], p["court_width"]),
                static_period_s=p["static_period"],
                convention=p["convention"] or None,
                world_frame=p["frame_id"],
            )
        except OSError as e:
            raise ConfigError(f"parameter 'port': {e}") from None
        self.start_diagnostics()
        self.poses_topic = self.resolve_topic_name(p["poses_topic"])
        self.subs = [self.create_subscription(PointCloud2, self.poses_topic, self.on_poses, DATA_QOS)]
        raw = p["image_transport"] == "raw"
        for cam in rig.names:
            image = self.resolve_topic_name(f"{cam}/image_raw" + ("" if raw else "/compressed"))
            info = self.resolve_topic_name(f"{cam}/camera_info")
            self.subs.append(
                self.create_subscription(
                    Image if raw else CompressedImage,
                    image,
                    lambda m, c=cam, t=image: self.on_image(c, t, m),  # type: ignore[misc]  # c, t bound
                    IMAGE_QOS,
                )
            )
            self.subs.append(
                self.create_subscription(
                    CameraInfo,
                    info,
                    lambda m, c=cam, t=info: self.on_info(c, t, m),  # type: ignore[misc]  # as above
                    IMAGE_QOS,
                )
            )
        # steady clock: with use_sim_time and no /clock yet a ROS-time timer would never fire
        self.timer = self.create_timer(
            p["static_period"], self.bridge.tick, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )
        self.diag.set("url", self.bridge.url)
        self.get_logger().info(
            f"Foxglove server on {self.bridge.url}: {self.poses_topic} and "
            f"{len(rig)} cameras ({p['image_transport']} images)"
        )

    def on_poses(self, msg: PointCloud2) -> None:
        self.diag.input(self.poses_topic)
        try:
            frame = wire.msg_to_poses(msg, self.poses_topic)
        except wire.WireError as e:
            self.diag.reject(e.reason, str(e))
            return
        with RejectErrors(self.diag, f"{self.poses_topic} {frame.stamp_ns}", "bad_poses") as step:
            with Stopwatch(self.diag, "publish_poses"):
                self.bridge.publish_poses(frame.stamp_ns, frame.ids, frame.joints, frame.frame_id)
        if not step.failed:
            self.diag.ok()

    def on_image(self, cam: str, topic: str, msg) -> None:
        self.diag.input(topic)
        with RejectErrors(self.diag, topic, "bad_image"):
            stamp = wire.checked_stamp_ns(msg.header.stamp, topic)
            if isinstance(msg, CompressedImage):
                self.bridge.publish_image(cam, stamp, bytes(msg.data), msg.format)
            else:
                self.bridge.publish_bgr(cam, stamp, wire.image_to_bgr(msg, topic))

    def on_info(self, cam: str, topic: str, msg: CameraInfo) -> None:
        self.diag.input(topic)
        with RejectErrors(self.diag, topic, "bad_camera_info"):
            stamp = wire.checked_stamp_ns(msg.header.stamp, topic)
            self.bridge.publish_calibration(cam, stamp, camera_info_fields(msg))

    def destroy_node(self) -> None:
        self.bridge.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return FoxgloveNode.main(args)


if __name__ == "__main__":
    sys.exit(main())
