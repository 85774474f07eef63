"""Foxglove messages (foxglove-sdk ``foxglove.messages``) for the rig and the tracked skeletons.

Frames: ``world`` is the rig's world (metres, court centre, z up); each camera's frame is named
after it, an optical frame (x right, y down, z forward) as in the rig's world->camera R, t.
Image coordinates are RAW (distorted) px, as in ``/<cam>/image_raw``. Stamps are integer ns.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from foxglove.messages import (
    CameraCalibration,
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    LinePrimitive,
    LinePrimitiveLineType,
    Point2,
    Point3,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextAnnotation,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from maem_ros.core.colors import id_rgb
from maem_ros.core.geometry import frames as frames_
from maem_ros.core.geometry.camera import Camera, Rig

WORLD = "world"
#: poses ``id`` of a person without a confirmed track, drawn grey without an id label (the value
#: of maem_ros.wire UNTRACKED_ID, kept apart so viz stays free of the wire; a test keeps them equal)
UNTRACKED_ID = 0xFFFFFFFF
#: Foxglove's names for the rig's distortion models
FOXGLOVE_DISTORTION = {
    "plumb_bob": "plumb_bob",
    "rational_polynomial": "rational_polynomial",
    "equidistant": "kannala_brandt",
}
_GREY = (0.6, 0.6, 0.6)
_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def timestamp(stamp_ns: int) -> Timestamp:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return Timestamp(sec, nsec)


def id_color(track_id: int, alpha: float = 1.0) -> Color:
    """The track id's colour (the overlays' and markers' id colour), grey when untracked."""
    if int(track_id) == UNTRACKED_ID or int(track_id) < 0:
        r, g, b = _GREY
    else:
        r, g, b = id_rgb(int(track_id))
    return Color(r=r, g=g, b=b, a=float(alpha))


def _pose(xyz: Sequence[float] = (0.0, 0.0, 0.0), q: Quaternion = _IDENTITY) -> Pose:
    return Pose(position=Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])), orientation=q)


def _points3(xyz: np.ndarray) -> list[Point3]:
    return [Point3(x=x, y=y, z=z) for x, y, z in np.asarray(xyz, dtype=np.float64).tolist()]


def _points2(uv: np.ndarray) -> list[Point2]:
    return [Point2(x=x, y=y) for x, y in np.asarray(uv, dtype=np.float64).tolist()]


def _bone_ends(finite: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """(B',2) bones of ``bones`` (B,2) whose two ends are finite (``finite`` (J,) bool)."""
    if not len(bones):
        return bones.reshape(0, 2)
    return bones[finite[bones[:, 0]] & finite[bones[:, 1]]]


# ---------------------------------------------------------------------------------------------
# 3D scene
# ---------------------------------------------------------------------------------------------
def skeletons_update(
    stamp_ns: int,
    ids: np.ndarray,
    joints: np.ndarray,
    bones: Sequence[tuple[int, int]],
    joint_diameter: float = 0.08,
    bone_width: float = 0.03,
    frame_id: str = WORLD,
) -> SceneUpdate:
    """One frame's people: per person a SceneEntity (``frame_id``, id ``person/<id>``, or
    ``untracked/<row>``) with a sphere per finite joint, a LINE_LIST of the bones whose ends are
    finite and the id as text 0.3 m above the highest joint, coloured by id.

    The update first deletes every entity older than this frame, so the previous frame's
    skeletons are replaced (no blinking at slow replay, no ghosts of vanished people).
    joints (P,J,3) world metres, NaN = missing.
    """
    ts = timestamp(stamp_ns)
    bones_arr = np.asarray(bones, dtype=np.int64).reshape(-1, 2)
    size = Vector3(x=joint_diameter, y=joint_diameter, z=joint_diameter)
    entities = []
    for row, (pid, pj) in enumerate(
        zip(np.asarray(ids, dtype=np.int64), np.asarray(joints, dtype=np.float64))
    ):
        finite = np.isfinite(pj).all(axis=1)
        if not finite.any():
            continue
        tracked = pid != UNTRACKED_ID and pid >= 0
        color = id_color(pid)
        spheres = [SpherePrimitive(pose=_pose(p), size=size, color=color) for p in pj[finite].tolist()]
        ends = _bone_ends(finite, bones_arr)
        lines = (
            [
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    pose=_pose(),
                    thickness=bone_width,
                    points=_points3(pj[ends.reshape(-1)]),
                    color=color,
                )
            ]
            if len(ends)
            else []
        )
        top = pj[finite][np.argmax(pj[finite][:, 2])]
        texts = (
            [
                TextPrimitive(
                    pose=_pose(top + [0.0, 0.0, 0.3]),
                    billboard=True,
                    font_size=0.25,
                    color=color,
                    text=str(int(pid)),
                )
            ]
            if tracked
            else []
        )
        entities.append(
            SceneEntity(
                timestamp=ts,
                frame_id=frame_id,
                id=f"person/{pid}" if tracked else f"untracked/{row}",
                spheres=spheres,
                lines=lines,
                texts=texts,
            )
        )
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)], entities=entities
    )


def frustum_corners(cam: Camera, depth: float) -> np.ndarray:
    """(4,3) image corners (0,0), (w,0), (w,h), (0,h) at ``depth`` m in the camera's frame."""
    uv1 = np.array(
        [[0, 0, 1], [cam.width, 0, 1], [cam.width, cam.height, 1], [0, cam.height, 1]], dtype=np.float64
    )
    return (uv1 @ np.linalg.inv(cam.K).T) * depth


def rig_update(
    stamp_ns: int,
    rig: Rig,
    court_size: tuple[float, float] = (28.0, 15.0),
    frustum_depth: float = 1.5,
    world: str = WORLD,
) -> SceneUpdate:
    """The static scene: the court floor (a ``court_size`` L x W m slab under z = 0, centred on
    the world origin, with its outline and centre line) and per camera a frustum (frame-locked
    to the camera's frame: apex, image corners at ``frustum_depth`` m, the name)."""
    ts = timestamp(stamp_ns)
    length, width = (float(v) for v in court_size)
    hx, hy = length / 2, width / 2
    floor_color = Color(r=0.72, g=0.55, b=0.36, a=0.6)
    line_color = Color(r=1.0, g=1.0, b=1.0, a=1.0)
    outline = np.array([[-hx, -hy, 0.005], [hx, -hy, 0.005], [hx, hy, 0.005], [-hx, hy, 0.005]])
    centre = np.array([[0.0, -hy, 0.005], [0.0, hy, 0.005]])
    entities = [
        SceneEntity(
            timestamp=ts,
            frame_id=world,
            id="court",
            frame_locked=True,
            cubes=[
                CubePrimitive(
                    pose=_pose((0.0, 0.0, -0.01)), size=Vector3(x=length, y=width, z=0.02), color=floor_color
                )
            ],
            lines=[
                LinePrimitive(
                    type=LinePrimitiveLineType.LineLoop,
                    pose=_pose(),
                    thickness=0.05,
                    points=_points3(outline),
                    color=line_color,
                ),
                LinePrimitive(
                    type=LinePrimitiveLineType.LineStrip,
                    pose=_pose(),
                    thickness=0.05,
                    points=_points3(centre),
                    color=line_color,
                ),
            ],
        )
    ]
    for k, cam in enumerate(rig):
        c = frustum_corners(cam, frustum_depth)
        segments = np.concatenate(
            [np.stack([np.zeros((4, 3)), c], axis=1), np.stack([c, np.roll(c, -1, axis=0)], axis=1)]
        ).reshape(-1, 3)
        color = id_color(k)
        entities.append(
            SceneEntity(
                timestamp=ts,
                frame_id=cam.name,
                id=f"camera/{cam.name}",
                frame_locked=True,
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineList,
                        pose=_pose(),
                        thickness=0.03,
                        points=_points3(segments),
                        color=color,
                    )
                ],
                texts=[
                    TextPrimitive(
                        pose=_pose((0.0, -0.2, 0.0)),
                        billboard=True,
                        font_size=0.3,
                        color=color,
                        text=cam.name,
                    )
                ],
            )
        )
    return SceneUpdate(entities=entities)


def rig_transforms(stamp_ns: int, frames: Sequence[frames_.FrameTransform]) -> FrameTransforms:
    """The rig's world -> camera transforms (``core.geometry.frames.rig_transforms``: translation = the
    camera centre, rotation = R^T) as Foxglove FrameTransforms at ``stamp_ns``."""
    ts = timestamp(stamp_ns)
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=ts,
                parent_frame_id=f.parent,
                child_frame_id=f.child,
                translation=Vector3(
                    x=float(f.translation[0]), y=float(f.translation[1]), z=float(f.translation[2])
                ),
                rotation=Quaternion(
                    x=float(f.quaternion[0]),
                    y=float(f.quaternion[1]),
                    z=float(f.quaternion[2]),
                    w=float(f.quaternion[3]),
                ),
            )
            for f in frames
        ]
    )


# ---------------------------------------------------------------------------------------------
# per camera
# ---------------------------------------------------------------------------------------------
def calibration(stamp_ns: int, frame_id: str, info: Mapping) -> CameraCalibration:
    """CameraCalibration from CameraInfo fields (``Camera.to_camera_info()`` or a received
    sensor_msgs/CameraInfo as a dict: width, height, distortion_model, d, k, r, p)."""
    model = str(info["distortion_model"])
    return CameraCalibration(
        timestamp=timestamp(stamp_ns),
        frame_id=frame_id,
        width=int(info["width"]),
        height=int(info["height"]),
        distortion_model=FOXGLOVE_DISTORTION.get(model, model),
        D=[float(v) for v in info["d"]],
        K=[float(v) for v in info["k"]],
        R=[float(v) for v in info["r"]],
        P=[float(v) for v in info["p"]],
    )


def camera_info_fields(msg) -> dict:
    """The CameraInfo fields :func:`calibration` reads, from a sensor_msgs/CameraInfo (rclpy or
    rosbags message)."""
    return {
        "width": int(msg.width),
        "height": int(msg.height),
        "distortion_model": str(msg.distortion_model),
        "d": list(msg.d),
        "k": list(msg.k),
        "r": list(msg.r),
        "p": list(msg.p),
    }


def image_format(fmt: str) -> str:
    """Foxglove's format name ('jpeg', 'png', 'webp') for a CompressedImage.format such as
    'jpeg' or 'bgr8; png compressed bgr8'; ValueError for anything else."""
    low = fmt.lower()
    for name, keys in (("png", ("png",)), ("jpeg", ("jpeg", "jpg")), ("webp", ("webp",))):
        if any(k in low for k in keys):
            return name
    raise ValueError(f"image format: {fmt!r} is not jpeg, png or webp")


def compressed_image(stamp_ns: int, frame_id: str, data: bytes, fmt: str) -> CompressedImage:
    return CompressedImage(
        timestamp=timestamp(stamp_ns), frame_id=frame_id, data=bytes(data), format=image_format(fmt)
    )


def skeleton_annotations(
    stamp_ns: int,
    cam: Camera,
    ids: np.ndarray,
    joints: np.ndarray,
    bones: Sequence[tuple[int, int]],
    thickness: float = 3.0,
) -> ImageAnnotations:
    """The 3D skeletons reprojected into ``cam``'s raw image: per person a LINE_LIST of the bones
    and a POINTS annotation of the joints (joints behind the camera or missing are left out),
    and the id above the topmost joint; coloured by id. joints (P,J,3) world metres."""
    ts = timestamp(stamp_ns)
    joints = np.asarray(joints, dtype=np.float64)
    uv = cam.project(joints) if joints.size else np.zeros((0, 0, 2))  # (P,J,2) NaN behind
    bones_arr = np.asarray(bones, dtype=np.int64).reshape(-1, 2)
    points, texts = [], []
    for pid, puv in zip(np.asarray(ids, dtype=np.int64), uv):
        finite = np.isfinite(puv).all(axis=1)
        if not finite.any():
            continue
        color = id_color(pid)
        ends = _bone_ends(finite, bones_arr)
        if len(ends):
            points.append(
                PointsAnnotation(
                    timestamp=ts,
                    type=PointsAnnotationType.LineList,
                    points=_points2(puv[ends.reshape(-1)]),
                    outline_color=color,
                    thickness=thickness,
                )
            )
        points.append(
            PointsAnnotation(
                timestamp=ts,
                type=PointsAnnotationType.Points,
                points=_points2(puv[finite]),
                outline_color=color,
                thickness=2 * thickness,
            )
        )
        if pid != UNTRACKED_ID and pid >= 0:
            top = puv[finite][np.argmin(puv[finite][:, 1])]
            texts.append(
                TextAnnotation(
                    timestamp=ts,
                    position=Point2(x=float(top[0]), y=float(top[1]) - 20.0),
                    text=str(int(pid)),
                    font_size=18.0,
                    text_color=color,
                    background_color=Color(r=0, g=0, b=0, a=0.5),
                )
            )
    return ImageAnnotations(points=points, texts=texts)
