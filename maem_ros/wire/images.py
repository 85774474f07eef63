"""Images: sensor_msgs/Image and CompressedImage decoded to BGR, and the rosbags messages a bag
writer takes (camera frames, CameraInfo). No rclpy; ros/wire builds the rclpy messages."""

from __future__ import annotations

from typing import Any

import numpy as np

from maem_ros import bagio
from maem_ros.core.geometry.camera import Camera
from maem_ros.wire.cdr import make_header
from maem_ros.wire.cloud import WireError

_IMAGE_CHANNELS = {"bgr8": 3, "rgb8": 3, "mono8": 1, "8UC1": 1, "8UC3": 3, "bgra8": 4, "rgba8": 4}
#: CompressedImage.format of JPEG frames (image_transport 'compressed' convention)
JPEG_FORMAT = "bgr8; jpeg compressed bgr8"
_T = bagio.TYPESTORE.types


def image_to_bgr(msg: Any, topic: str) -> np.ndarray:
    """sensor_msgs/Image (bgr8, rgb8, bgra8, rgba8, mono8) -> BGR uint8 (H,W,3)."""
    import cv2

    ch = _IMAGE_CHANNELS.get(msg.encoding)
    if ch is None:
        raise WireError(
            topic,
            "encoding",
            f"unsupported {msg.encoding!r}, expected one of {sorted(_IMAGE_CHANNELS)}",
            "bad_encoding",
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise WireError(topic, "height/width", f"empty image {w}x{h}", "bad_size")
    if step < w * ch or len(msg.data) != h * step:
        raise WireError(topic, "data", f"{len(msg.data)} bytes for {w}x{h}x{ch} with step {step}", "bad_size")
    rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(h, step)
    img = rows[:, : w * ch].reshape(h, w, ch)
    if ch == 1:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if msg.encoding in ("rgb8", "rgba8"):
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGR)
    return img[:, :, :3] if ch == 4 else img


def compressed_to_bgr(msg: Any, topic: str) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg, png, ...) -> BGR uint8 (H,W,3) via cv2.imdecode."""
    import cv2

    if len(msg.data) == 0:
        raise WireError(topic, "data", "empty", "bad_size")
    img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise WireError(
            topic, "data", f"cannot decode {len(msg.data)} bytes (format {msg.format!r})", "bad_encoding"
        )
    return img


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """BGR uint8 (H,W,3) -> JPEG bytes at ``quality`` (1..100)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("image: JPEG encoding failed")
    return buf.tobytes()


def compressed_image_msg(data: bytes, fmt: str, stamp_ns: int, frame_id: str) -> Any:
    """rosbags sensor_msgs/CompressedImage carrying encoded bytes unchanged (``fmt`` e.g.
    "jpeg", "png")."""
    return _T[bagio.COMPRESSED_IMAGE](
        header=make_header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(bytes(data), dtype=np.uint8)
    )


def bgr_to_compressed(image: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 90) -> Any:
    """BGR uint8 (H,W,3) -> rosbags sensor_msgs/CompressedImage, JPEG at ``quality``."""
    return compressed_image_msg(encode_jpeg(image, quality), JPEG_FORMAT, stamp_ns, frame_id)


def camera_info_msg(camera: Camera, stamp_ns: int, frame_id: str) -> Any:
    """Camera -> rosbags sensor_msgs/CameraInfo of the RAW image: K, D and distortion model;
    R = I; P = [K_rect | 0] of the rectified image the frontends work in."""
    info = camera.to_camera_info()
    roi = _T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _T[bagio.CAMERA_INFO](
        header=make_header(stamp_ns, frame_id),
        height=int(info["height"]),
        width=int(info["width"]),
        distortion_model=str(info["distortion_model"]),
        d=np.asarray(info["d"], np.float64),
        k=np.asarray(info["k"], np.float64),
        r=np.asarray(info["r"], np.float64),
        p=np.asarray(info["p"], np.float64),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
