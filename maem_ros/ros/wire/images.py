"""rclpy image, CameraInfo and TF messages (the codec, maem_ros.wire, builds rosbags ones)."""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from maem_ros.core.geometry.camera import Camera
from maem_ros.core.geometry.frames import FrameTransform
from maem_ros.ros.wire.clouds import make_header
from maem_ros.wire import tf as codec_tf
from maem_ros.wire.images import JPEG_FORMAT, encode_jpeg


def bgr_to_image(image: np.ndarray, stamp_ns: int, frame_id: str) -> Image:
    """BGR uint8 (H,W,3) -> sensor_msgs/Image bgr8."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = image.shape[:2]
    msg = Image(
        header=make_header(stamp_ns, frame_id), height=h, width=w, encoding="bgr8", is_bigendian=0, step=w * 3
    )
    msg.data = image.tobytes()
    return msg


def compressed_image_msg(data: bytes, fmt: str, stamp_ns: int, frame_id: str) -> CompressedImage:
    """sensor_msgs/CompressedImage carrying encoded bytes unchanged (``fmt`` e.g. "jpeg", "png")."""
    msg = CompressedImage(header=make_header(stamp_ns, frame_id), format=fmt)
    msg.data = bytes(data)
    return msg


def bgr_to_compressed(image: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 90) -> CompressedImage:
    """BGR uint8 (H,W,3) -> sensor_msgs/CompressedImage, JPEG at ``quality`` (1..100)."""
    return compressed_image_msg(encode_jpeg(image, quality), JPEG_FORMAT, stamp_ns, frame_id)


def camera_info_msg(camera: Camera, stamp_ns: int, frame_id: str) -> CameraInfo:
    """Camera -> sensor_msgs/CameraInfo of the RAW image: K, D and distortion model; R = I;
    P = [K_rect | 0] of the rectified image the frontends work in."""
    info = camera.to_camera_info()
    return CameraInfo(
        header=make_header(stamp_ns, frame_id),
        width=int(info["width"]),
        height=int(info["height"]),
        distortion_model=str(info["distortion_model"]),
        d=info["d"],
        k=info["k"],
        r=info["r"],
        p=info["p"],
    )


def _rclpy_type(msgtype: str) -> Any:
    """The rclpy class of ``pkg/msg/Name`` (tf2_msgs is optional: ImportError when absent)."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def tf_message(transforms: Sequence[FrameTransform], stamp_ns: int, types: Any = None) -> Any:
    """tf2_msgs/TFMessage of the transforms (maem_ros.wire.tf.tf_message), rclpy classes unless
    ``types`` (msgtype -> class, e.g. the rosbags typestore's) is given; ImportError if
    tf2_msgs is not installed."""
    return codec_tf.tf_message(transforms, stamp_ns, _rclpy_type if types is None else types)
