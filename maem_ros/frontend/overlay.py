"""Debug overlay: detections drawn on the rectified image (boxes, score/id, skeleton, mesh dots).

All coordinates in ``FrameDetections`` are rectified px, so the overlay must be
drawn on the rectified image (``Rectifier.rectify``), not on the raw one.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from maem_ros.core.colors import id_bgr8
from maem_ros.core.detections import FrameDetections
from maem_ros.core.skeleton import KeypointConvention, convention_for, get_convention

_LIMIT = 1 << 15  # cv2 drawing takes int coordinates; clamp far-off points well outside any image


def _resolve_convention(conv: KeypointConvention | str | None, num_joints: int) -> KeypointConvention | None:
    if isinstance(conv, KeypointConvention):
        if conv.num_joints != num_joints:
            raise ValueError(
                f"overlay: convention {conv.name!r} has {conv.num_joints} joints, "
                f"detections have {num_joints}"
            )
        return conv
    if isinstance(conv, str):
        return _resolve_convention(get_convention(conv), num_joints)
    try:
        return convention_for(num_joints)
    except ValueError:
        return None  # unknown layout: joints are drawn without bones


def _pt(p: np.ndarray) -> tuple[int, int]:
    q = np.clip(np.round(p), -_LIMIT, _LIMIT)
    return int(q[0]), int(q[1])


def _as_bgr(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise ValueError(
            f"overlay: expected an image array (H,W[,C]), got "
            f"{type(image).__name__} {getattr(image, 'shape', '')}"
        )
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 1:
        return cv2.cvtColor(image[..., 0], cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.shape[2] != 3:
        raise ValueError(f"overlay: expected 1, 3 or 4 channels, got {image.shape[2]}")
    return image.copy()


def draw_detections(
    image_rect: np.ndarray,
    dets: FrameDetections,
    ids: Sequence[int] | np.ndarray | None = None,
    convention: KeypointConvention | str | None = None,
    max_vertices: int = 0,
    thickness: int = 2,
) -> np.ndarray:
    """Draw ``dets`` on a copy of the rectified image and return it (BGR uint8, same H,W).

    Per detection: bbox, a label ``#<id> <score>`` (id = ``ids[i]`` when given, e.g. the
    cluster or track id, else the detection index; a negative id is drawn as ``?``),
    keypoints joined by the convention's bones (default: the convention with J joints),
    and up to ``max_vertices`` evenly spaced mesh vertices as dots (0 = none).
    Non-finite coordinates are skipped. Colour follows the id.
    """
    out = _as_bgr(image_rect)
    n = dets.n
    if ids is not None:
        ids = np.asarray(ids).ravel()
        if ids.shape[0] != n:
            raise ValueError(f"overlay: got {ids.shape[0]} ids for {n} detections")
    conv = _resolve_convention(convention, dets.num_joints) if n else None
    scale = max(0.4, min(out.shape[:2]) / 1000.0)
    for i in range(n):
        key = int(ids[i]) if ids is not None else i
        colour = id_bgr8(key) if key >= 0 else (160, 160, 160)
        if max_vertices > 0 and dets.num_vertices:
            _draw_vertices(out, dets.verts2d[i], max_vertices, colour)
        _draw_skeleton(out, dets.kpts2d[i], conv, colour, thickness)
        _draw_box(
            out, dets.bboxes[i], f"#{key if key >= 0 else '?'} {dets.scores[i]:.2f}", colour, thickness, scale
        )
    return out


def _draw_box(img: np.ndarray, box: np.ndarray, label: str, colour, thickness: int, scale: float) -> None:
    if not np.all(np.isfinite(box)):
        return
    p1, p2 = _pt(box[:2]), _pt(box[2:])
    cv2.rectangle(img, p1, p2, colour, thickness, cv2.LINE_AA)
    (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    y = p1[1] - 4 if p1[1] - th - 4 >= 0 else p1[1] + th + 4
    cv2.rectangle(img, (p1[0], y - th - 2), (p1[0] + tw + 2, y + base - 2), colour, cv2.FILLED)
    cv2.putText(img, label, (p1[0] + 1, y - 1), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _draw_skeleton(
    img: np.ndarray, kpts: np.ndarray, conv: KeypointConvention | None, colour, thickness: int
) -> None:
    ok = np.all(np.isfinite(kpts), axis=1)
    if conv is not None:
        for a, b in conv.bones:
            if ok[a] and ok[b]:
                cv2.line(img, _pt(kpts[a]), _pt(kpts[b]), colour, thickness, cv2.LINE_AA)
    for j in np.flatnonzero(ok):
        cv2.circle(img, _pt(kpts[j]), thickness + 1, colour, cv2.FILLED, cv2.LINE_AA)


def _draw_vertices(img: np.ndarray, verts: np.ndarray, max_vertices: int, colour) -> None:
    step = max(1, int(np.ceil(verts.shape[0] / max_vertices)))
    sub = verts[::step]
    sub = sub[np.all(np.isfinite(sub), axis=1)]
    h, w = img.shape[:2]
    px = np.round(sub).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    px = px[inside]
    dim = tuple(int(c * 0.6) for c in colour)
    img[px[:, 1], px[:, 0]] = dim
