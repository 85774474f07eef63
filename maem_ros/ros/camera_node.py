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

import glob as globmod
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from maem_ros.core.camera import Camera
from maem_ros.ros import wire
from maem_ros.core.paramspec import Params, param
from maem_ros.ros.common import (IMAGE_QOS, ConfigError, Diagnostics, Stopwatch,
                                 declare_params, default_camera_name, load_rig_param, run_node)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")
EXIT_SOURCE_FAILED = 2

@dataclass
class CameraNodeParams(Params):
    """The camera node's parameters (``source`` is declared separately: string or integer)."""

    camera: str = param("", "camera name: rig key, topic namespace /<camera>/ (default: the "
                            "last component of the node namespace)")
    rig: str = param("", "rig YAML / camera-JSON folder / shipped rig name; empty = no "
                         "camera_info")
    fps: float = param(30.0, "capture and publish rate, Hz", minimum=0.0, exclusive_minimum=True,
                       maximum=1000.0)
    transport: str = param("raw", "raw: /<camera>/image_raw (bgr8); compressed: "
                                  "/<camera>/image_raw/compressed (jpeg)",
                           choices=("raw", "compressed"))
    jpeg_quality: int = param(90, "JPEG quality for transport=compressed", minimum=1,
                              maximum=100)
    loop: bool = param(False, "restart a video file or image folder at its end (else exit 0)")
    frame_id: str = param("", "header.frame_id (default: the camera name)")
    reliability: str = param("reliable", "image/camera_info publisher QoS: reliable (matches "
                                         "every subscriber, incl. RViz) or best_effort (sensor "
                                         "data)", choices=("reliable", "best_effort"))
    open_attempts: int = param(5, "attempts to open a source that never opened before giving "
                                  "up (exit code 2)", minimum=1)
    open_timeout: float = param(5.0, "s, open/read timeout for stream URLs (FFmpeg backend)",
                                minimum=0.0, exclusive_minimum=True)
    reconnect_backoff: float = param(0.5, "s, first retry delay; doubles per failed attempt",
                                     minimum=0.0, exclusive_minimum=True)
    reconnect_backoff_max: float = param(10.0, "s, longest retry delay", minimum=0.0,
                                         exclusive_minimum=True)
    max_reconnects: int = param(0, "give up (exit 2) after this many failed reopen attempts of a "
                                   "source that was open (0 = retry forever)", minimum=0)


PARAMS = CameraNodeParams.specs()


# ---------------------------------------------------------------------------------------------
# frame sources
# ---------------------------------------------------------------------------------------------
class FrameSource(Protocol):
    """One openable image source. ``finite``: its end is normal (file/folder), not a failure."""

    description: str
    finite: bool

    def open(self) -> bool: ...

    def read(self) -> tuple[np.ndarray | None, int]:
        """(frame or None at end/failure, stamp ns taken right after the grab)."""

    def rewind(self) -> bool: ...

    def release(self) -> None: ...


def _natural_key(s: str):
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", s)]


class ImageFolderSource:
    """Images of a folder (known extensions) or a glob pattern, in natural order."""

    finite = True

    def __init__(self, pattern: str, clock_ns: Callable[[], int]):
        self.pattern = pattern
        self.description = f"image folder {pattern!r}"
        self._clock_ns = clock_ns
        self._files: list[str] = []
        self._index = 0

    def _list(self) -> list[str]:
        p = Path(self.pattern).expanduser()
        if p.is_dir():
            files = [str(f) for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS]
        else:
            files = [f for f in globmod.glob(str(p)) if os.path.isfile(f)]
        return sorted(files, key=_natural_key)

    def open(self) -> bool:
        self._files = self._list()
        self._index = 0
        return bool(self._files)

    def read(self) -> tuple[np.ndarray | None, int]:
        if self._index >= len(self._files):
            return None, 0
        path = self._files[self._index]
        self._index += 1
        stamp = self._clock_ns()
        frame = cv2.imread(path, cv2.IMREAD_COLOR)
        if frame is None:
            raise UnreadableFrame(f"unreadable image {path!r}, skipped")
        return frame, stamp

    def rewind(self) -> bool:
        self._index = 0
        return bool(self._files)

    def release(self) -> None:
        self._index = len(self._files)


class VideoSource:
    """cv2.VideoCapture on a device index, a video file or a stream URL."""

    def __init__(self, spec: str | int, clock_ns: Callable[[], int], open_timeout_s: float = 5.0):
        self.spec = spec
        self.finite = isinstance(spec, str) and "://" not in spec  # a local file ends; streams fail
        kind = "device" if isinstance(spec, int) else ("video file" if self.finite else "stream")
        self.description = f"{kind} {spec!r}"
        self._clock_ns = clock_ns
        self._timeout_ms = int(1000 * open_timeout_s)
        self._cap: cv2.VideoCapture | None = None

    def open(self) -> bool:
        self.release()
        if isinstance(self.spec, int):
            cap = cv2.VideoCapture(self.spec)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # newest frame, not a queued one (V4L2)
        else:
            target = str(Path(self.spec).expanduser()) if self.finite else self.spec
            cap = cv2.VideoCapture(target, cv2.CAP_ANY,
                                   [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self._timeout_ms,
                                    cv2.CAP_PROP_READ_TIMEOUT_MSEC, self._timeout_ms])
        if not cap.isOpened():
            cap.release()
            return False
        self._cap = cap
        return True

    def read(self) -> tuple[np.ndarray | None, int]:
        if self._cap is None or not self._cap.grab():
            return None, 0
        stamp = self._clock_ns()
        ok, frame = self._cap.retrieve()
        return (frame if ok and frame is not None else None), stamp

    def rewind(self) -> bool:
        return self.open()

    def release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def make_source(spec: str, clock_ns: Callable[[], int], open_timeout_s: float = 5.0) -> FrameSource:
    """The FrameSource for a ``source`` parameter value (see the module docstring)."""
    spec = spec.strip()
    if not spec:
        raise ConfigError("parameter 'source': empty; give a device index, video file, stream "
                          "URL or image folder/glob")
    if re.fullmatch(r"\d+", spec):
        return VideoSource(int(spec), clock_ns, open_timeout_s)
    p = Path(spec).expanduser()
    if p.is_dir() or (not p.exists() and any(c in spec for c in "*?[") and "://" not in spec):
        return ImageFolderSource(spec, clock_ns)
    return VideoSource(spec, clock_ns, open_timeout_s)


# ---------------------------------------------------------------------------------------------
# open / read / reconnect state machine (no ROS; clock passed in)
# ---------------------------------------------------------------------------------------------
class UnreadableFrame(OSError):
    """One bad frame of a source that is otherwise fine (e.g. a corrupt file in a folder):
    skipped and counted, the source is not reopened."""


@dataclass
class Poll:
    """Result of one capture tick: a frame, or status 'skipped' | 'waiting' | 'ended' | 'failed'."""

    status: str
    frame: np.ndarray | None = None
    stamp_ns: int = 0
    message: str = ""


@dataclass
class CaptureCounters:
    opens: int = 0
    open_failures: int = 0
    reconnects: int = 0
    read_failures: int = 0
    skipped: int = 0
    loops: int = 0
    frames: int = 0


@dataclass
class Capture:
    """Opens ``source``, reads frames, reopens after failures with exponential backoff.

    Delays (s): after the k-th consecutive failed attempt the next one waits
    ``min(backoff * 2**(k-1), backoff_max)``. A source never opened fails for good after
    ``open_attempts`` failed attempts; one that was open retries forever unless
    ``max_reconnects`` > 0 consecutive reopen attempts failed.
    """

    source: FrameSource
    loop: bool = False
    open_attempts: int = 5
    backoff: float = 0.5
    backoff_max: float = 10.0
    max_reconnects: int = 0
    counters: CaptureCounters = field(default_factory=CaptureCounters)

    def __post_init__(self) -> None:
        self._open = False
        self._ever_opened = False
        self._failed_attempts = 0
        self._next_attempt = -float("inf")
        self._final: Poll | None = None

    @property
    def is_open(self) -> bool:
        return self._open

    def delay(self, failed_attempts: int) -> float:
        """s to wait after ``failed_attempts`` consecutive failures (>= 1)."""
        return min(self.backoff * 2.0 ** (failed_attempts - 1), self.backoff_max)

    def poll(self, now: float) -> Poll:
        """One tick at monotonic time ``now`` (s)."""
        if self._final is not None:
            return self._final
        if not self._open:
            result = self._try_open(now)
            if result is not None:
                return result
        try:
            frame, stamp = self.source.read()
            if frame is None and self.source.finite:
                if not self.loop:
                    return self._finish(Poll("ended", message=f"end of {self.source.description}"))
                self.counters.loops += 1
                if not self.source.rewind():
                    return self._lost(now, "cannot restart at its end")
                frame, stamp = self.source.read()
        except UnreadableFrame as e:
            self.counters.skipped += 1
            return Poll("skipped", message=str(e))
        except OSError as e:
            return self._lost(now, str(e))
        if frame is None:
            return self._lost(now, "read failed")
        self.counters.frames += 1
        return Poll("frame", frame, stamp)

    def _try_open(self, now: float) -> Poll | None:
        if now < self._next_attempt:
            return Poll("waiting")
        if self.source.open():
            self._open = True
            self.counters.opens += 1
            if self._ever_opened:
                self.counters.reconnects += 1
            self._ever_opened = True
            self._failed_attempts = 0
            return None
        self.counters.open_failures += 1
        self._failed_attempts += 1
        if not self._ever_opened and self._failed_attempts >= self.open_attempts:
            return self._finish(Poll("failed", message=(
                f"cannot open {self.source.description} after {self._failed_attempts} attempts; "
                "check the path/URL/device index and that nothing else holds the device")))
        if self._ever_opened and 0 < self.max_reconnects <= self._failed_attempts:
            return self._finish(Poll("failed", message=(
                f"lost {self.source.description}; {self._failed_attempts} reopen attempts failed")))
        self._next_attempt = now + self.delay(self._failed_attempts)
        return Poll("waiting", message=f"cannot open {self.source.description}, retrying in "
                                       f"{self.delay(self._failed_attempts):.1f} s")

    def _lost(self, now: float, why: str) -> Poll:
        self.counters.read_failures += 1
        self.source.release()
        self._open = False
        self._next_attempt = now  # first reopen immediately, then back off
        return Poll("waiting", message=f"{self.source.description}: {why}; reconnecting")

    def _finish(self, result: Poll) -> Poll:
        self.source.release()
        self._open = False
        self._final = result
        return result

    def close(self) -> None:
        self.source.release()
        self._open = False


# ---------------------------------------------------------------------------------------------
# messages not (yet) in wire.py: JPEG CompressedImage and CameraInfo from the rig
# ---------------------------------------------------------------------------------------------
def to_bgr(frame: np.ndarray) -> np.ndarray:
    """Any uint8 mono / BGR / BGRA capture -> BGR uint8 (H,W,3)."""
    if frame.dtype != np.uint8:
        raise ValueError(f"image: expected uint8 pixels, got {frame.dtype}")
    if frame.ndim == 2 or frame.shape[2] == 1:
        return cv2.cvtColor(frame.reshape(frame.shape[:2]), cv2.COLOR_GRAY2BGR)
    return cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR) if frame.shape[2] == 4 else frame


def bgr_to_compressed(image: np.ndarray, stamp_ns: int, frame_id: str,
                      quality: int) -> CompressedImage:
    """BGR uint8 -> sensor_msgs/CompressedImage, JPEG (image_transport 'compressed' format)."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("image: JPEG encoding failed")
    msg = CompressedImage(header=wire.make_header(stamp_ns, frame_id),
                          format="bgr8; jpeg compressed bgr8")
    msg.data = buf.tobytes()
    return msg


def camera_info_msg(camera: Camera, stamp_ns: int, frame_id: str) -> CameraInfo:
    """Camera -> sensor_msgs/CameraInfo (raw image K, D, model; R = I; P = [K_rect | 0])."""
    info = camera.to_camera_info()
    return CameraInfo(header=wire.make_header(stamp_ns, frame_id), width=info["width"],
                      height=info["height"], distortion_model=info["distortion_model"],
                      d=info["d"], k=info["k"], r=info["r"], p=info["p"])


# ---------------------------------------------------------------------------------------------
# node
# ---------------------------------------------------------------------------------------------
class CameraNode(Node):
    """Timer-driven capture -> image (+ camera_info) publisher for one camera."""

    def __init__(self, **kwargs):
        super().__init__("camera", **kwargs)
        p = declare_params(self, PARAMS)
        p["source"] = self._declare_source()
        self.camera_name = p["camera"] or default_camera_name(self)
        if not self.camera_name:
            raise ConfigError("parameter 'camera': empty and the node has no namespace to take "
                              "the name from")
        self.frame_id = p["frame_id"] or self.camera_name
        self.camera = self._load_camera(p["rig"])
        self.transport, self.jpeg_quality = p["transport"], p["jpeg_quality"]
        clock = self.get_clock()
        source = make_source(p["source"], lambda: clock.now().nanoseconds, p["open_timeout"])
        self.capture = Capture(source, loop=p["loop"], open_attempts=p["open_attempts"],
                               backoff=p["reconnect_backoff"],
                               backoff_max=p["reconnect_backoff_max"],
                               max_reconnects=p["max_reconnects"])
        base = f"/{self.camera_name}"
        qos = QoSProfile(depth=IMAGE_QOS.depth, history=HistoryPolicy.KEEP_LAST,
                         reliability=(ReliabilityPolicy.RELIABLE if p["reliability"] == "reliable"
                                      else ReliabilityPolicy.BEST_EFFORT))
        if self.transport == "raw":
            self.pub_image = self.create_publisher(Image, f"{base}/image_raw", qos)
        else:
            self.pub_image = self.create_publisher(CompressedImage, f"{base}/image_raw/compressed",
                                                   qos)
        self.pub_info = (self.create_publisher(CameraInfo, f"{base}/camera_info", qos)
                         if self.camera is not None else None)
        self.diag = Diagnostics(self, hardware_id=self.camera_name)
        self.diag.set("source", source.description)
        self.done: Future = Future()
        self._size_warned = False
        self._last_message = ""
        self.timer = self.create_timer(1.0 / p["fps"], self._tick)
        self.get_logger().info(f"{source.description} -> {self.pub_image.topic_name} at "
                               f"{p['fps']:g} Hz ({self.transport})")

    def _declare_source(self) -> str:
        """``source`` takes a string or an integer (``source:=0`` parses as an int)."""
        desc = ParameterDescriptor(
            name="source", description="device index (0), video file, stream URL, or image "
            "folder / glob", dynamic_typing=True, read_only=True)
        value = self.declare_parameter("source", "", desc).value
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"parameter 'source': expected a device index or a string, "
                              f"got {value!r}")
        if isinstance(value, int) and value < 0:
            raise ConfigError(f"parameter 'source': device index {value} is negative")
        return str(value)

    def _load_camera(self, rig_value: str) -> Camera | None:
        if not rig_value:
            self.get_logger().warning("parameter 'rig' is empty: publishing images without "
                                      "camera_info")
            return None
        rig = load_rig_param(rig_value)
        if self.camera_name not in rig:
            raise ConfigError(f"parameter 'camera': {self.camera_name!r} is not in rig "
                              f"{rig_value!r} ({rig.names})")
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
        if result.message and result.message != self._last_message and \
                result.status in ("waiting", "skipped"):
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
                    f"{self.camera.width}x{self.camera.height}: camera_info does not match")
        with Stopwatch(self.diag, "encode"):
            bgr = to_bgr(frame)
            if self.transport == "raw":
                msg = wire.bgr_to_image(bgr, stamp_ns, self.frame_id)
            else:
                msg = bgr_to_compressed(bgr, stamp_ns, self.frame_id, self.jpeg_quality)
        self.pub_image.publish(msg)
        if self.pub_info is not None:
            self.pub_info.publish(camera_info_msg(self.camera, stamp_ns, self.frame_id))
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
    return run_node(CameraNode, args, "maem-camera", until=lambda node: node.done)


if __name__ == "__main__":
    sys.exit(main())
