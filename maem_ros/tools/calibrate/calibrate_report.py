"""The people calibration's report: a per-camera table on stdout, and with ``--report DIR`` a
top-down picture of the rig and the people's floor tracks (rig.png) and, where the source has
images, one overlay per camera of the observed (green) and reprojected (magenta) keypoints."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TextIO

import numpy as np

from maem_ros.core.calibrate.people import PeopleCalibration
from maem_ros.core.calibrate.people_data import PeopleData


def print_summary(result: PeopleCalibration, data: PeopleData, out: TextIO) -> None:
    print(
        f"{'camera':<14}{'obs':>7}{'median px':>11}{'p90 px':>9}{'rot sd deg':>12}"
        f"{'centre sd cm':>14}{'offset ms':>11}{'sd ms':>7}",
        file=out,
    )
    for c in result.cameras:
        if not c.calibrated:
            print(f"{c.name:<14}  NOT CALIBRATED", file=out)
            continue
        print(
            f"{c.name:<14}{c.observations:>7d}{c.median_px:>11.2f}{c.p90_px:>9.2f}"
            f"{c.rotation_sd_deg:>12.3f}{100 * c.centre_sd_m:>14.2f}{1000 * c.time_offset_s:>11.1f}"
            f"{1000 * c.time_offset_sd_s:>7.1f}",
            file=out,
        )
    print(f"scale from: {result.scale_source}", file=out)
    for w in result.warnings:
        print(f"warning: {w}", file=out)


def write_report(result: PeopleCalibration, data: PeopleData, folder: Path, images: dict) -> list[Path]:
    """Write rig.png and the overlays; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = [_top_down(result, data, folder / "rig.png", plt)]
    for cam in result.rig:
        frame = _overlay_frame(images, cam.name, result)
        if frame is not None:
            written.append(
                _overlay(
                    result, data, cam, frame, images[(cam.name, frame)], folder / f"overlay_{cam.name}.jpg"
                )
            )
    return written


def _top_down(result: PeopleCalibration, data: PeopleData, path: Path, plt) -> Path:
    fig, ax = plt.subplots(figsize=(9, 7))
    X = result.points
    feet = X[:, :, data.feet] if data.feet.size else X
    with warnings.catch_warnings():  # frames without feet: NaN, not drawn
        warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of all-NaN
        floor = np.nanmean(feet, axis=2)  # (T,F,3)
    for tr in floor:
        ok = np.all(np.isfinite(tr), axis=1)
        if ok.sum() >= 2:
            ax.plot(tr[ok, 0], tr[ok, 1], lw=0.8, alpha=0.7)
    for cam in result.rig:
        c = cam.center
        look = cam.R[2]
        ax.plot(c[0], c[1], "k^", ms=9)
        ax.arrow(c[0], c[1], 3 * look[0], 3 * look[1], head_width=0.5, color="k")
        ax.annotate(
            f"{cam.name}\n{c[2]:.1f} m high",
            (c[0], c[1]),
            textcoords="offset points",
            xytext=(6, 6),
            fontsize=8,
        )
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"calibrated rig (top view) and people's floor tracks; scale: {result.scale_source}")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _overlay_frame(images: dict, cam: str, result: PeopleCalibration) -> int | None:
    """The frame with images whose tracks hold the most points."""
    frames = [k for (c, k) in images if c == cam]
    if not frames:
        return None
    count = np.isfinite(result.points[..., 0]).sum(axis=(0, 2))
    return max(frames, key=lambda k: count[k] if k < count.size else -1)


def _overlay(
    result: PeopleCalibration, data: PeopleData, cam, frame: int, image_path: Path, path: Path
) -> Path:
    import cv2

    img = cv2.imread(str(image_path))
    if img is None:
        raise ValueError(f"image {str(image_path)!r}: unreadable")
    X = result.points[:, frame].reshape(-1, 3)
    uv = cam.project(X[np.all(np.isfinite(X), axis=1)])  # raw px, as the image
    for u, v in uv[np.all(np.isfinite(uv), axis=1)]:
        cv2.circle(img, (int(round(u)), int(round(v))), 4, (255, 0, 255), 1, cv2.LINE_AA)
    c = data.rig.index(cam.name)
    obs = data.cameras[c].kpts2d[data.cameras[c].frame(frame)].reshape(-1, 2)
    obs = obs[np.all(np.isfinite(obs), axis=1)]
    raw = data.rig[c].distort_points(obs) if obs.size else obs
    for u, v in raw:
        cv2.circle(img, (int(round(u)), int(round(v))), 2, (0, 255, 0), -1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)
    return path
