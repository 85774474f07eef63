"""Synthetic camera rigs around a basketball court (world: origin at the court centre, z up, metres).

* ``sportcenter6``: 6 elevated cameras ~15 m from the centre, 5-8 m high, looking down at the
  court, image sizes 1328x896 .. 1536x1200, strong radial OpenCV plumb_bob distortion modelled on
  the SportCenter EPFL calibration (k1 ~ -0.35, k2 ~ 0.12).
* ``humanm3_4`` / ``humanm3_3``: 4 / 3 person-height (1.4-2 m) pinhole cameras near the court
  corners, 2048x1536, f ~ 1200 px, 20-35 m from the centre, as in Human-M3.
* ``lab4``: 4 cameras on a 3 m ring, 1.6-2.2 m high, around a volume at the origin, 800x600,
  f ~ 560 px, moderate radial distortion (k1 ~ -0.2): a room for calibration-board sequences.

``python -m maem_ros.sim.rigs [OUT_DIR]`` writes the rig YAMLs (default: config/rigs/).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from maem_ros.core.geometry.camera import Camera, Rig

COURT_LENGTH = 28.0  # m, along world x
COURT_WIDTH = 15.0  # m, along world y
#: basket centres (x, y, z) in world metres (rim 3.05 m high, 1.575 m in from the baseline)
BASKETS = np.array([[-COURT_LENGTH / 2 + 1.575, 0.0, 3.05], [COURT_LENGTH / 2 - 1.575, 0.0, 3.05]])

RIG_NAMES = ("sportcenter6", "humanm3_4", "humanm3_3", "lab4")


def court_corners(margin: float = 0.0, z: float = 0.0) -> np.ndarray:
    """(4,3) court corners in world metres, grown by ``margin`` m on every side."""
    hx, hy = COURT_LENGTH / 2 + margin, COURT_WIDTH / 2 + margin
    return np.array([[-hx, -hy, z], [hx, -hy, z], [hx, hy, z], [-hx, hy, z]], dtype=np.float64)


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World->camera (R, t) for an OpenCV camera (x right, y down, z forward) at ``eye``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])
    return R, -R @ eye


def _camera(
    name: str,
    eye,
    target,
    size: tuple[int, int],
    f: float,
    D=(0.0,) * 5,
    roll: float = 0.0,
    pp_shift: tuple[float, float] = (0.0, 0.0),
    aspect: float = 1.0,
) -> Camera:
    w, h = size
    K = np.array(
        [[f, 0.0, (w - 1) / 2 + pp_shift[0]], [0.0, f * aspect, (h - 1) / 2 + pp_shift[1]], [0.0, 0.0, 1.0]]
    )
    R, t = look_at(np.asarray(eye, float), np.asarray(target, float), roll)
    return Camera(
        name=name, K=K, R=R, t=t, width=w, height=h, distortion_model="plumb_bob", D=np.asarray(D, float)
    )


# sportcenter6: (eye xyz, target xyz, (w, h), f px, k1, k2, p1, p2, k3, roll rad, principal point shift px)
_SPORTCENTER6 = [
    (
        (-6.8, -12.8, 7.1),
        (-4.0, -4.5, 0.0),
        (1376, 992),
        648.0,
        -0.34,
        0.12,
        -0.004,
        0.0008,
        -0.012,
        0.010,
        (-9.0, -20.0),
    ),
    (
        (6.9, -13.0, 7.4),
        (3.0, -2.0, 0.0),
        (1536, 1200),
        720.0,
        -0.31,
        0.10,
        0.002,
        -0.0010,
        -0.010,
        -0.008,
        (6.0, -14.0),
    ),
    (
        (16.2, -2.5, 6.4),
        (8.0, -1.0, 0.0),
        (1328, 896),
        625.0,
        -0.36,
        0.13,
        -0.003,
        0.0006,
        -0.014,
        0.012,
        (12.0, -10.0),
    ),
    (
        (7.0, 12.9, 7.3),
        (3.0, 2.0, 0.0),
        (1376, 992),
        646.0,
        -0.35,
        0.124,
        -0.0068,
        -0.0006,
        -0.0125,
        -0.006,
        (0.0, -18.0),
    ),
    (
        (-7.1, 12.8, 6.9),
        (-3.0, 2.0, 0.0),
        (1456, 1088),
        684.0,
        -0.33,
        0.115,
        0.005,
        0.0012,
        -0.011,
        0.009,
        (-14.0, -16.0),
    ),
    (
        (-16.3, 2.5, 6.3),
        (-8.0, 1.0, 0.0),
        (1328, 896),
        625.0,
        -0.37,
        0.135,
        0.001,
        -0.0004,
        -0.015,
        -0.011,
        (8.0, -10.0),
    ),
]


def sportcenter6() -> Rig:
    """6 elevated, strongly distorted cameras around the court (like SportCenter EPFL)."""
    cams = [
        _camera(f"camera_{i}", eye, tgt, size, f, (k1, k2, p1, p2, k3), roll, pp, aspect=1.015)
        for i, (eye, tgt, size, f, k1, k2, p1, p2, k3, roll, pp) in enumerate(_SPORTCENTER6)
    ]
    return Rig(cams)


def _humanm3(n: int) -> Rig:
    # person-height tripods beyond the court corners, pinhole, like Human-M3's basketball scenes
    spec = [
        ((-24.0, -15.0, 1.55), (-1.0, 0.0, 0.9), 1204.6, 0.004),
        ((25.5, -14.0, 1.80), (1.0, 0.0, 0.9), 1198.3, -0.006),
        ((23.0, 16.5, 1.45), (1.0, 0.0, 0.9), 1210.2, 0.003),
        ((-26.0, 13.0, 1.70), (-1.0, 0.0, 0.9), 1195.8, -0.002),
    ]
    if n == 3:
        spec = [spec[0], spec[1], spec[2]]
    cams = [
        _camera(f"camera_{i}", eye, tgt, (2048, 1536), f, roll=roll, pp_shift=(-1.3, 12.0), aspect=1.0002)
        for i, (eye, tgt, f, roll) in enumerate(spec)
    ]
    return Rig(cams)


def lab4() -> Rig:
    """4 cameras around a room-sized volume (a board-calibration rig), distorted."""
    # (eye xyz, f px, k1, k2, p1, p2, roll rad, principal point shift px)
    spec = [
        ((3.0, 0.2, 1.8), 560.0, -0.21, 0.06, 0.0008, -0.0005, 0.01, (6.0, -4.0)),
        ((0.3, 3.1, 2.2), 548.0, -0.19, 0.05, -0.0006, 0.0004, -0.02, (-5.0, 3.0)),
        ((-2.9, -0.4, 1.6), 575.0, -0.23, 0.07, 0.0003, 0.0007, 0.015, (3.0, 5.0)),
        ((-0.2, -3.0, 2.0), 555.0, -0.20, 0.055, -0.0004, -0.0003, -0.01, (-4.0, -6.0)),
    ]
    cams = [
        _camera(
            f"camera_{i}", eye, (0.0, 0.0, 1.0), (800, 600), f, (k1, k2, p1, p2, 0.0), roll, pp, aspect=1.004
        )
        for i, (eye, f, k1, k2, p1, p2, roll, pp) in enumerate(spec)
    ]
    return Rig(cams)


def build_rig(name: str) -> Rig:
    """The named synthetic rig, computed (no file access)."""
    builders = {
        "sportcenter6": sportcenter6,
        "humanm3_4": lambda: _humanm3(4),
        "humanm3_3": lambda: _humanm3(3),
        "lab4": lab4,
    }
    if name not in builders:
        raise ValueError(f"rig: unknown synthetic rig {name!r}, expected one of {sorted(builders)}")
    return builders[name]()


def load_rig(name_or_path: str) -> Rig:
    """A shipped rig by name (config/rigs/NAME.yaml, else built in code) or a rig file/folder path."""
    from ..params import resolve_rig_path

    try:
        return Rig.load(resolve_rig_path(name_or_path))
    except ValueError:
        if name_or_path in RIG_NAMES:
            return build_rig(name_or_path)
        raise


def write_rigs(out_dir: str | Path) -> list[Path]:
    """Write every synthetic rig as ``OUT_DIR/<name>.yaml``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in RIG_NAMES:
        p = out / f"{name}.yaml"
        build_rig(name).to_yaml(p)
        paths.append(p)
    return paths


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).resolve().parents[2] / "config" / "rigs"
    for p in write_rigs(out):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
