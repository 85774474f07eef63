"""maem-camera: capture from an OpenCV source, publish /<cam>/image_raw[/compressed] + camera_info.

Sources (parameter ``source``): a device index (``0``), a video file, a stream URL
(``rtsp://...``, ``http://...``), or an image folder / glob (``frames/*.jpg``, natural order).
Frames are read by a timer at ``fps`` and stamped with the node clock right after the grab.
A live source that fails is reopened with exponential backoff (``reconnect_backoff`` doubling
up to ``reconnect_backoff_max``); a source that never opens within ``open_attempts`` attempts
ends the node with one clear error line and exit code 2. A file or folder ends the node with
exit code 0 at its end unless ``loop`` is true. Publisher QoS: keep last 2, reliable by default
(a reliable publisher matches both reliable subscribers such as RViz and the best-effort frontend);
``reliability:=best_effort`` for lossy links.

CameraInfo comes from the rig (``rig`` parameter, entry ``camera``): K, D and the distortion
model of the RAW image, P = [K_rect | 0] of the rectified image the frontend produces.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from maem_ros.capture import Capture, Poll, make_source, to_bgr
from maem_ros.core.geometry.camera import Camera
from maem_ros.core.paramspec import Params, ParamSpec, param
from maem_ros.ros import wire
from maem_ros.ros.diagnostics import Stopwatch
from maem_ros.ros.node import MaemNode
from maem_ros.ros.params import ConfigError, default_camera_name, load_rig_param
from maem_ros.ros.qos import IMAGE_QOS

EXIT_SOURCE_FAILED = 2


@dataclass
class CameraNodeParams(Params):
    """The camera node's parameters (``source`` is declared separately: string or integer)."""

    camera: str = param(
        "",
        "camera name: rig key, topic namespace /<camera>/ (default: the "
        "last component of the node namespace)",
    )
    rig: str = param("", "rig YAML / camera-JSON folder / shipped rig name; empty = no camera_info")
    fps: float = param(
        30.0, "capture and publish rate, Hz", minimum=0.0, exclusive_minimum=True, maximum=1000.0
    )
    transport: str = param(
        "raw",
        "raw: /<camera>/image_raw (bgr8); compressed: /<camera>/image_raw/compressed (jpeg)",
        choices=("raw", "compressed"),
    )
    jpeg_quality: int = param(90, "JPEG quality for transport=compressed", minimum=1, maximum=100)
    loop: bool = param(False, "restart a video file or image folder at its end (else exit 0)")
    frame_id: str = param("", "header.frame_id (default: the camera name)")
    reliability: str = param(
        "reliable",
        "image/camera_info publisher QoS: reliable (matches "
        "every subscriber, incl. RViz) or best_effort (sensor "
        "data)",
        choices=("reliable", "best_effort"),
    )
    open_attempts: int = param(
        5, "attempts to open a source that never opened before giving up (exit code 2)", minimum=1
    )
    open_timeout: float = param(
        5.0, "s, open/read timeout for stream URLs (FFmpeg backend)", minimum=0.0, exclusive_minimum=True
    )
    reconnect_backoff: float = param(
        0.5, "s, first retry delay; doubles per failed attempt", minimum=0.0, exclusive_minimum=True
    )
    reconnect_backoff_max: float = param(10.0, "s, longest retry delay", minimum=0.0, exclusive_minimum=True)
    max_reconnects: int = param(
        0,
        "give up (exit 2) after this many failed reopen attempts of a "
        "source that was open (0 = retry forever)",
        minimum=0,
    )


PARAMS = CameraNodeParams.specs()
#: ``source`` takes a string or an integer (``source:=0`` parses as an int): declared on its own
SOURCE = ParamSpec("source", "", "device index (0), video file, stream URL, or image folder / glob")


# ---------------------------------------------------------------------------------------------
# node
# ---------------------------------------------------------------------------------------------
class CameraNode(MaemNode):
    """Timer-driven capture -> image (+ camera_info) publisher for one camera."""

    # ``source`` is declared by the node itself (string or integer device index)
    NAME, PARAMS, HELP_PARAMS = "camera", PARAMS, (SOURCE,) + PARAMS

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        p = self.p
        p["source"] = self._declare_source()
        self.camera_name = p["camera"] or default_camera_name(self)
        if not self.camera_name:
            raise ConfigError("parameter 'camera': empty and the node has no namespace to take the name from")
        self.frame_id = p["frame_id"] or self.camera_name
        self.camera = self._load_camera(p["rig"])
        self.transport, self.jpeg_quality = p["transport"], p["jpeg_quality"]
        clock = self.get_clock()
        try:
            source = make_source(p["source"], lambda: clock.now().nanoseconds, p["open_timeout"])
        except ValueError as e:
            raise ConfigError(f"parameter 'source': {e}") from None
        self.capture = Capture(
            source,
            loop=p["loop"],
            open_attempts=p["open_attempts"],
            backoff=p["reconnect_backoff"],
            backoff_max=p["reconnect_backoff_max"],
            max_reconnects=p["max_reconnects"],
        )
        # relative names under the node's namespace: image_raw... in the camera's own namespace
        # (/<camera>), else <camera>/image_raw... (/<camera>/... for a node in /)
        base = "" if default_camera_name(self) == self.camera_name else f"{self.camera_name}/"
        qos = QoSProfile(
            depth=IMAGE_QOS.depth,
            history=HistoryPolicy.KEEP_LAST,
            reliability=(
                ReliabilityPolicy.RELIABLE
                if p["reliability"] == "reliable"
                else ReliabilityPolicy.BEST_EFFORT
            ),
        )
        if self.transport == "raw":
            self.pub_image = self.create_publisher(Image, f"{base}image_raw", qos)
        else:
            self.pub_image = self.create_publisher(CompressedImage, f"{base}image_raw/compressed", qos)
        self.pub_info = (
            self.create_publisher(CameraInfo, f"{base}camera_info", qos) if self.camera is not None else None
        )
        self.start_diagnostics(hardware_id=self.camera_name)
        self.diag.set("source", source.description)
        self.done: Future = Future()
        self._size_warned = False
        self._last_message = ""
        self.timer = self.create_timer(1.0 / p["fps"], self._tick)
        self.get_logger().info(
            f"{source.description} -> {self.pub_image.topic_name} at {p['fps']:g} Hz ({self.transport})"
        )

    def _declare_source(self) -> str:
        """``source`` takes a string or an integer (``source:=0`` parses as an int)."""
        desc = ParameterDescriptor(
            name="source", description=SOURCE.description, dynamic_typing=True, read_only=True
        )
        value = self.declare_parameter("source", "", desc).value
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"parameter 'source': expected a device index or a string, got {value!r}")
        if isinstance(value, int) and value < 0:
            raise ConfigError(f"parameter 'source': device index {value} is negative")
        return str(value)

    def _load_camera(self, rig_value: str) -> Camera | None:
        if not rig_value:
            self.get_logger().warning("parameter 'rig' is empty: publishing images without camera_info")
            return None
        rig = load_rig_param(rig_value)
        if self.camera_name not in rig:
            raise ConfigError(
                f"parameter 'camera': {self.camera_name!r} is not in rig {rig_value!r} ({rig.names})"
            )
        return rig[self.camera_name]

    def _tick(self) -> None:
        if self.done.done():
            return
        result = self.capture.poll(time.monotonic())
        self._report(result)
        if result.status == "frame":
            self._publish(result.frame, result.stamp_ns)
        elif result.status == "ended":
            self.get_logger().info(result.message)
            self._finish(0)
        elif result.status == "failed":
            self.get_logger().error(result.message)
            print(f"[maem-camera] {self.camera_name}: {result.message}", file=sys.stderr, flush=True)
            self._finish(EXIT_SOURCE_FAILED)

    def _report(self, result: Poll) -> None:
        c = self.capture.counters
        for name in ("opens", "open_failures", "reconnects", "read_failures", "skipped", "loops"):
            self.diag.set(f"count/{name}", getattr(c, name))
        if result.status == "skipped":
            self.diag.drop("unreadable_frame")
        if (
            result.message
            and result.message != self._last_message
            and result.status in ("waiting", "skipped")
        ):
            self.get_logger().warning(result.message)
        self._last_message = result.message

    def _publish(self, frame: np.ndarray, stamp_ns: int) -> None:
        h, w = frame.shape[:2]
        if self.camera is not None and (w, h) != (self.camera.width, self.camera.height):
            self.diag.count("size_mismatch")
            if not self._size_warned:
                self._size_warned = True
                self.get_logger().error(
                    f"frames are {w}x{h} but the rig calibration of {self.camera_name!r} is "
                    f"{self.camera.width}x{self.camera.height}: camera_info does not match"
                )
        with Stopwatch(self.diag, "encode"):
            bgr = to_bgr(frame)
            if self.transport == "raw":
                msg = wire.bgr_to_image(bgr, stamp_ns, self.frame_id)
            else:
                msg = wire.bgr_to_compressed(bgr, stamp_ns, self.frame_id, self.jpeg_quality)
        self.pub_image.publish(msg)
        if self.pub_info is not None:
            self.pub_info.publish(wire.camera_info_msg(self.camera, stamp_ns, self.frame_id))
        self.diag.input("capture")
        self.diag.ok()

    def _finish(self, code: int) -> None:
        self.timer.cancel()
        self.capture.close()
        self.done.set_result(code)

    def destroy_node(self) -> None:
        self.capture.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Spin the node until its source ends (0) or fails (2), a bad parameter (2), or SIGINT (0)."""
    return CameraNode.main(args, until=lambda node: node.done)  # type: ignore[attr-defined]  # a CameraNode


if __name__ == "__main__":
    sys.exit(main())
