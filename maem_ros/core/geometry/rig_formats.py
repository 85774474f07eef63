"""Other systems' calibration files <-> camera parameters: Qualisys ``.qca.txt``, Pose2Sim ``Calib*.toml``.

Both readers return plain camera parameters in our convention, one dict per camera holding the
keyword arguments of :class:`core.geometry.camera.Camera` (``name``, ``K`` OpenCV pinhole px,
``R``, ``t`` world -> camera in metres, ``width``, ``height`` px, ``distortion_model``, ``D``,
``time_offset`` s): :class:`Camera` validates them and :meth:`Rig.load` builds the cameras. This
module does not import camera.py (camera.py's Rig.load imports it), and the writer takes any
object with a camera's attributes (:class:`CameraLike`).

Qualisys (QTM export, XML), read the way Pose2Sim's converter (``Pose2Sim.calibration.read_qca``
+ ``calib_qca_fun``) reads it:

* focal lengths and principal point are in sensor units of 1/64 px; the principal point is
  relative to the sensor, so the ``fov_video`` left/top offset is subtracted;
* k1 k2 p1 p2 are divided by 64 as well (Pose2Sim does; the coefficients in QTM exports are
  scaled with the sensor units), k3 is not used;
* ``transform`` holds the camera pose in the world: position x y z (mm) and a rotation r11..r33
  written by column (camera -> world once transposed); world -> camera is the r matrix as written
  by row, followed by a rotation of pi about the camera x axis (QTM cameras look along -z with y
  up; OpenCV looks along +z with y down), t = -R @ position;
* image size = fov_video (right - left + 1) x (bottom - top + 1);
* ``viewrotation`` (0, 90, 180, 270 degrees, clockwise: the delivered video is the sensor image
  rotated by it) rotates the pinhole camera about its optical axis (K, size, distortion, R, t);
* cameras are sorted by serial in natural order.

Qualisys cameras are hardware-synchronised: their ``time_offset`` is 0.

Pose2Sim TOML (``[cam_name]`` tables with size, matrix, distortions k1 k2 p1 p2 (k3 and, for
rational_polynomial, k4-k6 may follow, as anipose writes them), rotation as a Rodrigues vector
and translation in metres, both world -> camera, fisheye false; a ``[metadata]`` table is skipped;
an optional ``time_offset`` (s, this project's key, ignored by Pose2Sim and anipose) is kept).
:func:`write_pose2sim_toml` writes the same layout.
"""

from __future__ import annotations

import json
import math
import re
import sys
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: QTM sensor units per pixel
QUALISYS_SUBPIXELS = 64.0
#: pi about the camera x axis: QTM camera axes -> OpenCV camera axes
_QTM_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


#: one camera's parameters: the keyword arguments of core.geometry.camera.Camera
CameraParams = dict[str, Any]


class CameraLike(Protocol):
    """What :func:`pose2sim_toml_text` reads of a camera (core.geometry.camera.Camera has it)."""

    name: str
    K: np.ndarray  # (3,3) px
    R: np.ndarray  # (3,3) world -> camera
    t: np.ndarray  # (3,) world -> camera, metres
    D: np.ndarray  # distortion coefficients
    width: int  # px
    height: int  # px
    time_offset: float  # s

    @property
    def is_fisheye(self) -> bool: ...


def _natural_key(s: str) -> list:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]


def _attr(tag: ET.Element, key: str, where: str) -> float:
    value = tag.get(key)
    if value is None:
        raise ValueError(f"{where}: missing attribute {key!r} on <{tag.tag}>")
    try:
        out = float(value)
    except ValueError:
        raise ValueError(f"{where}: attribute {key!r} = {value!r} is not a number") from None
    if not np.isfinite(out):
        raise ValueError(f"{where}: attribute {key!r} = {value!r} is not finite")
    return out


def _child(cam: ET.Element, name: str, where: str) -> ET.Element:
    tag = cam.find(name)
    if tag is None:
        raise ValueError(f"{where}: no <{name}> element")
    return tag


def rotate_view(
    K: np.ndarray, D: np.ndarray, R: np.ndarray, t: np.ndarray, size: tuple[int, int], degrees: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """The same physical camera whose delivered image is rotated clockwise by ``degrees``
    (0/90/180/270): new K, D (k1 k2 p1 p2), R, t (world -> new camera) and (width, height).

    A clockwise quarter turn maps pixel (u, v) of a W x H image to (H-1-v, u): the camera axes
    turn about z (x' = -y, y' = x), fx and fy swap, the principal point moves along, radial
    distortion is unchanged and the tangential terms turn with the axes (p1' = p2, p2' = -p1).
    """
    if degrees not in (0, 90, 180, 270):
        raise ValueError(f"viewrotation: expected 0, 90, 180 or 270, got {degrees}")
    K, D, R, t = K.copy(), D.copy(), R.copy(), t.copy()
    w, h = size
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for _ in range(degrees // 90):
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        K = np.array([[fy, 0.0, h - 1 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
        D[2], D[3] = D[3], -D[2]
        R, t = quarter @ R, quarter @ t
        w, h = h, w
    return K, D, R, t, (w, h)


def read_qualisys(path: str | Path, binning: int = 1) -> list[CameraParams]:
    """Camera parameters of a Qualisys ``.qca.txt`` calibration (see the module doc for the conversion).

    ``binning``: sensor pixels per video pixel (2 when filming binned 540p on a 1080p sensor).
    """
    path = Path(path)
    where = f"qualisys calibration {str(path)!r}"
    try:
        root = ET.parse(path).getroot()
    except OSError as e:
        raise ValueError(f"{where}: cannot read ({e.strerror})") from None
    except ET.ParseError as e:
        raise ValueError(f"{where}: not valid XML ({e})") from None
    cams = root.findall("cameras/camera")
    if not cams:
        raise ValueError(f"{where}: no <cameras><camera> elements")
    out = [_qualisys_camera(cam, f"{where} camera {i}", binning) for i, cam in enumerate(cams)]
    names = [c["name"] for c in out]
    if len(set(names)) != len(names):
        raise ValueError(f"{where}: duplicate camera serials {names}")
    return sorted(out, key=lambda c: _natural_key(c["name"]))


def _qualisys_camera(cam: ET.Element, where: str, binning: int) -> CameraParams:
    name = cam.get("serial") or ""
    if not name:
        raise ValueError(f"{where}: camera without a serial")
    where = f"{where.rsplit(' camera ', 1)[0]} camera {name!r}"
    fov = _child(cam, "fov_video", where)
    left, top = _attr(fov, "left", where), _attr(fov, "top", where)
    size = (
        int(round((_attr(fov, "right", where) - left + 1) / binning)),
        int(round((_attr(fov, "bottom", where) - top + 1) / binning)),
    )
    intr = _child(cam, "intrinsic", where)
    scale = QUALISYS_SUBPIXELS * binning
    fx, fy = _attr(intr, "focalLengthU", where) / scale, _attr(intr, "focalLengthV", where) / scale
    cx = _attr(intr, "centerPointU", where) / scale - left
    cy = _attr(intr, "centerPointV", where) / scale - top
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    D = (
        np.array(
            [
                _attr(intr, k, where)
                for k in (
                    "radialDistortion1",
                    "radialDistortion2",
                    "tangentalDistortion1",
                    "tangentalDistortion2",
                )
            ]
        )
        / scale
    )
    tr = _child(cam, "transform", where)
    # r_ij at row i, column j: Pose2Sim reads it by column (its transpose) as the camera pose and
    # inverts that (transposes back) to world -> camera
    rows = np.array([[_attr(tr, f"r{i}{j}", where) for j in (1, 2, 3)] for i in (1, 2, 3)])
    position = np.array([_attr(tr, k, where) for k in ("x", "y", "z")]) / 1000.0
    R = _QTM_TO_OPENCV @ rows
    t = -R @ position
    rotation = cam.get("viewrotation", "0")
    try:
        degrees = int(float(rotation))
    except ValueError:
        raise ValueError(f"{where}: viewrotation {rotation!r} is not a number") from None
    K, D, R, t, size = rotate_view(K, D, R, t, size, degrees)
    return dict(
        name=name,
        K=K,
        R=R,
        t=t,
        width=size[0],
        height=size[1],
        distortion_model="plumb_bob",
        D=D,
        time_offset=0.0,
    )


def read_pose2sim_toml(path: str | Path) -> list[CameraParams]:
    """Camera parameters of a Pose2Sim calibration TOML (``Calib*.toml``), in file order."""
    path = Path(path)
    where = f"pose2sim calibration {str(path)!r}"
    try:
        data = tomllib.loads(path.read_text())
    except OSError as e:
        raise ValueError(f"{where}: cannot read ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{where}: not valid TOML ({e})") from None
    cams = [
        _pose2sim_camera(key, table, where)
        for key, table in data.items()
        if key != "metadata" and isinstance(table, dict)
    ]
    if not cams:
        raise ValueError(
            f"{where}: no camera tables (expected [cam_name] with size, matrix, "
            f"distortions, rotation, translation)"
        )
    return cams


def _pose2sim_camera(key: str, table: Mapping, where: str) -> CameraParams:
    name = str(table.get("name") or key)
    where = f"{where} camera {name!r}"
    missing = [k for k in ("size", "matrix", "distortions", "rotation", "translation") if k not in table]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    try:
        size = [float(v) for v in table["size"]]
        rvec = np.asarray(table["rotation"], dtype=np.float64).reshape(3)
        D = np.asarray(table["distortions"], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"{where}: size, rotation and distortions must be lists of numbers") from None
    if len(size) != 2:
        raise ValueError(f"{where}: size must be [width, height], got {table['size']}")
    fisheye = bool(table.get("fisheye", False))
    model = "equidistant" if fisheye else "rational_polynomial" if D.size > 5 else "plumb_bob"
    R = cv2.Rodrigues(rvec)[0]
    return dict(
        name=name,
        K=table["matrix"],
        R=R,
        t=table["translation"],
        width=int(round(size[0])),
        height=int(round(size[1])),
        distortion_model=model,
        D=D,
        time_offset=table.get("time_offset", 0.0),
    )


def _toml_value(value) -> str:
    """A float / bool / list of those as TOML (floats by repr: they read back bit-identical)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[ " + ", ".join(_toml_value(v) for v in value) + ",]"
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"pose2sim toml: {x} cannot be written")
    return repr(x)


def _toml_key(name: str) -> str:
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else json.dumps(name)


def pose2sim_toml_text(cameras: Sequence[CameraLike], error_px: float | None = None) -> str:
    """A Pose2Sim/anipose ``Calib.toml`` for ``cameras`` (layout in the module doc).

    Per camera: name, size [w, h], matrix (K), distortions (k1 k2 p1 p2, then k3.. only when
    non-zero), rotation (Rodrigues, world -> camera), translation (m), fisheye, and
    ``time_offset`` (s) when non-zero. ``[metadata]``: adjusted = false, error = ``error_px``
    (reprojection RMS, px; 0.0 when unknown) as Pose2Sim writes it. ``K_rect`` (a rectified
    image's intrinsics) has no place in this format and is not written.
    """
    tables = []
    for cam in cameras:
        D = [float(d) for d in cam.D]
        keep = 4 if cam.is_fisheye else max(4, max((i + 1 for i, d in enumerate(D) if d), default=0))
        rvec = cv2.Rodrigues(cam.R)[0].ravel()
        lines = [
            f"[{_toml_key(cam.name)}]",
            f"name = {json.dumps(cam.name)}",
            f"size = {_toml_value([float(cam.width), float(cam.height)])}",
            f"matrix = {_toml_value([list(row) for row in cam.K])}",
            f"distortions = {_toml_value(D[:keep])}",
            f"rotation = {_toml_value(list(rvec))}",
            f"translation = {_toml_value(list(cam.t))}",
            f"fisheye = {_toml_value(cam.is_fisheye)}",
        ]
        if cam.time_offset:
            lines.append(f"time_offset = {_toml_value(cam.time_offset)}")
        tables.append("\n".join(lines))
    tables.append(f"[metadata]\nadjusted = false\nerror = {_toml_value(error_px or 0.0)}")
    return "\n\n".join(tables) + "\n"


def write_pose2sim_toml(
    path: str | Path, cameras: Sequence[CameraLike], error_px: float | None = None
) -> None:
    """Write ``cameras`` as a Pose2Sim/anipose ``Calib.toml`` (see :func:`pose2sim_toml_text`)."""
    if any(c.name == "metadata" for c in cameras):
        raise ValueError("pose2sim toml: a camera named 'metadata' clashes with the metadata table")
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"pose2sim toml: duplicate camera names {names}")
    Path(path).write_text(pose2sim_toml_text(cameras, error_px))


def is_calibration_file(path: Path) -> bool:
    """True for file names this module reads (``*.qca.txt``, ``*.toml``)."""
    name = path.name.lower()
    return name.endswith(".qca.txt") or name.endswith(".toml")


def read_calibration(path: str | Path) -> list[CameraParams]:
    """Camera parameters of a ``.qca.txt`` or Pose2Sim ``.toml`` file (by name)."""
    p = Path(path)
    if p.name.lower().endswith(".qca.txt"):
        return read_qualisys(p)
    if p.name.lower().endswith(".toml"):
        return read_pose2sim_toml(p)
    raise ValueError(f"calibration {str(p)!r}: expected a Qualisys .qca.txt or a Pose2Sim .toml")
