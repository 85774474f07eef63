"""Which parts of the people a camera sees (sim/noise.py's visibility test): each person's
surface samples are projected; a sample is visible when it is inside the raw image and not
covered by a part box (per body part bbox, rectified px) of a person nearer to the camera."""

from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.camera import Camera

from .view import (
    camera_to_normalised_xy,
    camera_to_rectified_xy,
    inside_image_xy,
    normalised_to_raw_xy,
    world_to_camera,
)


def visibility(
    camera: Camera, sample_world: np.ndarray, part_of_sample: np.ndarray, num_parts: int
) -> tuple[np.ndarray, np.ndarray]:
    """Visible and in-image fractions (P,) of persons given their surface samples (P,S,3) world m.

    Occluders are the per-part boxes (rectified px) of persons whose root is nearer the camera.
    """
    vis, in_img, _ = sample_view(camera, sample_world, part_of_sample, num_parts)
    return vis, in_img


def sample_view(
    camera: Camera, sample_world: np.ndarray, part_of_sample: np.ndarray, num_parts: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``visibility`` plus the rectified v (P,S) px of the samples (NaN behind the camera)."""
    Xc = world_to_camera(camera, sample_world)
    in_img = inside_image_xy(camera, *normalised_to_raw_xy(camera, *camera_to_normalised_xy(camera, Xc)))
    u, v = camera_to_rectified_xy(camera, Xc)
    depth = Xc[..., 2].mean(axis=1)  # (P,)
    boxes = _part_boxes(u, v, part_of_sample, num_parts)
    occluded = _occluded(u, v, boxes, depth[None, :] < depth[:, None])  # nearer persons only
    visible = in_img & ~occluded
    return visible.mean(axis=1), in_img.mean(axis=1), v


def _part_boxes(u: np.ndarray, v: np.ndarray, part_of_sample: np.ndarray, num_parts: int) -> np.ndarray:
    """(P,K,4) px boxes (u0, v0, u1, v1) of each person's samples (P,S) per part, ignoring NaN
    samples; NaN for a part without finite samples."""
    keep = np.flatnonzero((part_of_sample >= 0) & (part_of_sample < num_parts))
    order = keep[np.argsort(part_of_sample[keep], kind="stable")]
    present, starts = np.unique(part_of_sample[order], return_index=True)
    boxes = np.full((u.shape[0], num_parts, 4), np.nan)
    if len(present):
        us, vs = u[:, order], v[:, order]
        for c, (fn, vals) in enumerate(((np.fmin, us), (np.fmin, vs), (np.fmax, us), (np.fmax, vs))):
            boxes[:, present, c] = fn.reduceat(vals, starts, axis=1)  # fmin/fmax: NaN only if all are
    return boxes


def _occluded(u: np.ndarray, v: np.ndarray, boxes: np.ndarray, nearer: np.ndarray) -> np.ndarray:
    """(P,S) samples (px u, v (P,S)) inside a part box (P,K,4) of a person q with nearer[p, q].

    Only pairs whose sample extent overlaps the occluder's overall box are compared.
    """
    P, S = u.shape
    ext = np.stack(
        [np.fmin.reduce(u, 1), np.fmin.reduce(v, 1), np.fmax.reduce(u, 1), np.fmax.reduce(v, 1)], 1
    )
    whole = np.stack(
        [
            np.fmin.reduce(boxes[..., 0], 1),
            np.fmin.reduce(boxes[..., 1], 1),
            np.fmax.reduce(boxes[..., 2], 1),
            np.fmax.reduce(boxes[..., 3], 1),
        ],
        1,
    )
    with np.errstate(invalid="ignore"):
        overlap = (
            (ext[:, None, 0] <= whole[None, :, 2])
            & (ext[:, None, 2] >= whole[None, :, 0])
            & (ext[:, None, 1] <= whole[None, :, 3])
            & (ext[:, None, 3] >= whole[None, :, 1])
        )
        pp, qq = np.nonzero(nearer & overlap)
        up, vp, b = u[pp][:, :, None], v[pp][:, :, None], boxes[qq][:, None]  # (M,S,1), (M,1,K,4)
        cover = ((up >= b[..., 0]) & (up <= b[..., 2]) & (vp >= b[..., 1]) & (vp <= b[..., 3])).any(axis=2)
    occluded = np.zeros((P, S), bool)
    np.logical_or.at(occluded, pp, cover)
    return occluded
