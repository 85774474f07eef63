"""The Foxglove WebSocket server and its channels (foxglove-sdk), fed by the live node or a bag.

Channels (schema; the Foxglove app's 3D and Image panels show them as they are):

===========================  ==========================  ======================================
topic                        schema                      content
===========================  ==========================  ======================================
/maem/skeletons              foxglove.SceneUpdate        per person joints (spheres), bones
                                                         (lines), id (text), coloured by id
/maem/rig                    foxglove.SceneUpdate        court floor and camera frustums
/tf                          foxglove.FrameTransforms    world -> every camera (from the rig)
/<cam>/image_raw/compressed  foxglove.CompressedImage    the camera's images (raw ones
                                                         JPEG-encoded)
/<cam>/camera_info           foxglove.CameraCalibration  K, D, R, P of the raw image
/<cam>/skeletons_2d          foxglove.ImageAnnotations   the 3D skeletons reprojected into
                                                         the camera
===========================  ==========================  ======================================

The rig scene, transforms and calibrations have no "latched" delivery in the protocol, so they
are sent again whenever a client subscribes and every ``static_period_s`` after that.
Message log times are the data's stamps (ns), so Foxglove's timeline shows recording time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping

import foxglove
import numpy as np
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    FrameTransformsChannel,
    ImageAnnotationsChannel,
    SceneUpdateChannel,
)
from foxglove.websocket import ServerListener

from maem_ros.core.geometry.camera import Rig
from maem_ros.core.geometry.frames import rig_transforms
from maem_ros.core.skeleton import convention_for, get_convention
from maem_ros.viz import scene

SKELETONS_TOPIC = "/maem/skeletons"
RIG_TOPIC = "/maem/rig"
TF_TOPIC = "/tf"


def image_topic(cam: str) -> str:
    return f"/{cam}/image_raw/compressed"


def calibration_topic(cam: str) -> str:
    return f"/{cam}/camera_info"


def annotations_topic(cam: str) -> str:
    return f"/{cam}/skeletons_2d"


class _Listener(ServerListener):
    """Marks the static messages due when any client subscribes to anything."""

    def __init__(self, bridge: FoxgloveBridge):
        self._bridge = bridge

    def on_subscribe(self, client, channel) -> None:
        self._bridge._on_subscribe()

    def on_unsubscribe(self, client, channel) -> None:
        return None


class FoxgloveBridge:
    """A foxglove-sdk WebSocket server on its own Context with the channels above.

    ``port`` 0 picks a free port (see :attr:`port`). Skeleton bones come from the keypoint
    convention with the poses' joint count (``convention`` names it when that is ambiguous).
    ``world_frame`` is the rig's world: parent of the camera transforms, frame of the court and,
    unless the poses name another, of the skeletons.
    Thread-safe: calls may come from ROS callbacks or a playback loop.
    """

    def __init__(
        self,
        rig: Rig,
        host: str = "127.0.0.1",
        port: int = 8765,
        court_size: tuple[float, float] = (28.0, 15.0),
        static_period_s: float = 1.0,
        convention: str | None = None,
        world_frame: str = scene.WORLD,
        name: str = "maem_ros",
    ):
        self.rig = rig
        self.world_frame = world_frame
        self._frames = rig_transforms(rig, world_frame)
        self.convention = get_convention(convention) if convention else None
        self.court_size = court_size
        self.static_period_s = float(static_period_s)
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self._statics_due = True
        self._last_statics = -np.inf
        self._last_stamp_ns = 0
        self._live_calibration: dict[str, Mapping] = {}
        self.context = foxglove.Context()
        ctx = self.context
        self.skeletons = SceneUpdateChannel(SKELETONS_TOPIC, context=ctx)
        self.rig_scene = SceneUpdateChannel(RIG_TOPIC, context=ctx)
        self.tf = FrameTransformsChannel(TF_TOPIC, context=ctx)
        self.images = {c.name: CompressedImageChannel(image_topic(c.name), context=ctx) for c in rig}
        self.calibrations = {
            c.name: CameraCalibrationChannel(calibration_topic(c.name), context=ctx) for c in rig
        }
        self.annotations = {
            c.name: ImageAnnotationsChannel(annotations_topic(c.name), context=ctx) for c in rig
        }
        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, context=ctx, server_listener=_Listener(self)
            )
        except Exception as e:  # noqa: BLE001 - the SDK raises its own error types
            raise OSError(f"cannot listen on {host}:{port} ({e})") from None
        self.host = host

    # -- server ---------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def wait_for_client(self, timeout_s: float | None = None) -> bool:
        """Block until a client subscribed to a channel (True) or ``timeout_s`` passed."""
        return self._subscribed.wait(timeout_s)

    def close(self) -> None:
        self.server.stop()

    def _on_subscribe(self) -> None:
        with self._lock:
            self._statics_due = True
        self._subscribed.set()

    # -- publishing -----------------------------------------------------------------------------
    def tick(self, stamp_ns: int | None = None) -> None:
        """Send the static messages if a client subscribed since, or every static period."""
        now = time.monotonic()
        with self._lock:
            if stamp_ns is not None:
                self._last_stamp_ns = max(self._last_stamp_ns, int(stamp_ns))
            due = self._statics_due or now - self._last_statics >= self.static_period_s
            if not due:
                return
            self._statics_due, self._last_statics = False, now
            stamp = self._last_stamp_ns
            live = dict(self._live_calibration)
        self.rig_scene.log(
            scene.rig_update(stamp, self.rig, self.court_size, world=self.world_frame), log_time=stamp
        )
        self.tf.log(scene.rig_transforms(stamp, self._frames), log_time=stamp)
        for cam in self.rig:
            info = live.get(cam.name, cam.to_camera_info())
            self.calibrations[cam.name].log(scene.calibration(stamp, cam.name, info), log_time=stamp)

    def publish_poses(self, stamp_ns: int, ids: np.ndarray, joints: np.ndarray, frame_id: str = "") -> None:
        """One poses frame (in ``frame_id``, '' = the world frame): 3D skeletons, transforms and
        every camera's 2D reprojection.
        joints (P,J,3) world m (NaN = missing); ValueError when no keypoint convention has J
        joints (or J differs from ``convention``'s)."""
        joints = np.asarray(joints, dtype=np.float64)
        bones = self.bones_for(joints.shape[1]) if joints.ndim == 3 and len(joints) else ()
        self.tick(stamp_ns)
        self.skeletons.log(
            scene.skeletons_update(stamp_ns, ids, joints, bones, frame_id=frame_id or self.world_frame),
            log_time=stamp_ns,
        )
        self.tf.log(scene.rig_transforms(stamp_ns, self._frames), log_time=stamp_ns)
        for cam in self.rig:
            self.annotations[cam.name].log(
                scene.skeleton_annotations(stamp_ns, cam, ids, joints, bones), log_time=stamp_ns
            )

    def bones_for(self, num_joints: int) -> tuple[tuple[int, int], ...]:
        conv = self.convention or convention_for(num_joints)
        if conv.num_joints != num_joints:
            raise ValueError(f"poses: {num_joints} joints, convention {conv.name} has {conv.num_joints}")
        return conv.bones

    def publish_image(self, cam: str, stamp_ns: int, data: bytes, fmt: str) -> None:
        """An encoded image (jpeg/png/webp bytes) of camera ``cam``."""
        self._channel(self.images, cam).log(
            scene.compressed_image(stamp_ns, cam, data, fmt), log_time=stamp_ns
        )
        self.tick(stamp_ns)

    def publish_bgr(self, cam: str, stamp_ns: int, image_bgr: np.ndarray, jpeg_quality: int = 90) -> None:
        """A decoded BGR uint8 (H,W,3) image, sent JPEG-encoded."""
        import cv2

        ok, jpg = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise ValueError(f"camera {cam!r}: JPEG encoding of a {image_bgr.shape} image failed")
        self.publish_image(cam, stamp_ns, jpg.tobytes(), "jpeg")

    def publish_calibration(self, cam: str, stamp_ns: int, info: Mapping) -> None:
        """A received CameraInfo (dict with width, height, distortion_model, d, k, r, p): sent
        now and from then on instead of the rig's intrinsics."""
        msg = scene.calibration(stamp_ns, cam, info)
        self._channel(self.calibrations, cam).log(msg, log_time=stamp_ns)
        with self._lock:
            self._live_calibration[cam] = dict(info)

    def _channel(self, channels: Mapping, cam: str):
        if cam not in channels:
            raise ValueError(f"camera {cam!r}: not in the rig ({', '.join(channels)})")
        return channels[cam]
