"""Calibrated cameras and rigs: projection, undistortion, epipolar geometry, file I/O.

Conventions: world points in metres; extrinsics R, t map world -> camera
(X_cam = R @ X_world + t); pixels are (u, v) with the origin at the top-left
pixel centre as in OpenCV. "Raw" pixels are in the distorted image the camera
delivers; "rectified" pixels are in the ideal pinhole image with intrinsics
``K_rect`` (equal to ``K`` unless configured otherwise).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from maem_ros.core.geometry.rig_formats import is_calibration_file, read_calibration

#: distortion model name -> number of coefficients, in CameraInfo order
DISTORTION_MODELS: dict[str, int] = {
    "plumb_bob": 5,  # k1 k2 p1 p2 k3
    "rational_polynomial": 8,  # k1 k2 p1 p2 k3 k4 k5 k6
    "equidistant": 4,  # fisheye k1 k2 k3 k4 (cv2.fisheye)
}

# 20 iterations reach ~1e-6 px on the authors' strongly distorted SportCenter lens; more only
# costs time (the npz frontend undistorts 12 x 18,439 vertices per frame)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)


def _as_matrix(value, shape: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size != int(np.prod(shape)):
        raise ValueError(f"{what}: expected {shape} values, got shape {arr.shape}")
    arr = arr.reshape(shape)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: contains NaN or inf")
    return arr


def _check_intrinsics(name: str, label: str, K: np.ndarray) -> None:
    """Pinhole intrinsics: fx, fy > 0, K[1,0] = 0, bottom row [0, 0, 1] (projection code and P
    must agree on the pixel grid)."""
    if not (
        K[0, 0] > 0 and K[1, 1] > 0 and abs(K[1, 0]) < 1e-9 and np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9)
    ):
        raise ValueError(
            f"camera {name!r} {label}: not pinhole intrinsics [[fx,s,cx],[0,fy,cy],"
            f"[0,0,1]] with fx, fy > 0: {K.tolist()}"
        )


@dataclass
class Camera:
    """One calibrated camera (intrinsics, world->camera extrinsics, distortion)."""

    name: str
    K: np.ndarray  # (3,3) px
    R: np.ndarray  # (3,3) world->camera rotation
    t: np.ndarray  # (3,) world->camera translation, metres
    width: int
    height: int
    distortion_model: str = "plumb_bob"
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    #: (3,3) intrinsics of the rectified image, an np.ndarray after __post_init__; None (the
    #: default) = a copy of K. Typed Any: the constructor takes None, the instance never has it
    K_rect: Any = None
    #: s, added to this camera's message stamps to give its true capture time (a camera whose
    #: stamps run 40 ms early has +0.04); core.sync.capture_stamp_ns applies it
    time_offset: float = 0.0

    def __post_init__(self) -> None:
        self.K = _as_matrix(self.K, (3, 3), f"camera {self.name!r} K")
        self.R = _as_matrix(self.R, (3, 3), f"camera {self.name!r} R")
        self.t = _as_matrix(self.t, (3,), f"camera {self.name!r} t")
        self.K_rect = (
            self.K.copy()
            if self.K_rect is None
            else _as_matrix(self.K_rect, (3, 3), f"camera {self.name!r} K_rect")
        )
        for label, K in (("K", self.K), ("K_rect", self.K_rect)):
            _check_intrinsics(self.name, label, K)
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(
                f"camera {self.name!r} distortion_model: unknown {self.distortion_model!r}, "
                f"expected one of {sorted(DISTORTION_MODELS)}"
            )
        n = DISTORTION_MODELS[self.distortion_model]
        d = np.asarray(self.D, dtype=np.float64).ravel()
        if d.size > n and np.any(d[n:] != 0):
            raise ValueError(
                f"camera {self.name!r} D: {self.distortion_model} takes {n} "
                f"coefficients, got {d.size} with non-zero extras"
            )
        self.D = np.concatenate([d[:n], np.zeros(max(0, n - d.size))])
        if not np.all(np.isfinite(self.D)):
            raise ValueError(f"camera {self.name!r} D: contains NaN or inf")
        ortho_err = np.abs(self.R @ self.R.T - np.eye(3)).max()
        if ortho_err > 1e-3 or abs(np.linalg.det(self.R) - 1.0) > 1e-3:
            raise ValueError(
                f"camera {self.name!r} R: not a rotation (det={np.linalg.det(self.R):.4f}, "
                f"max |R R^T - I| = {ortho_err:.2g})"
            )
        try:
            self.time_offset = float(self.time_offset)
        except (TypeError, ValueError):
            raise ValueError(
                f"camera {self.name!r} time_offset: {self.time_offset!r} is not a number of seconds"
            ) from None
        if not np.isfinite(self.time_offset):
            raise ValueError(f"camera {self.name!r} time_offset: {self.time_offset} is not finite")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r} image size: {self.width}x{self.height} is not positive")

    # ---- geometry -------------------------------------------------------
    @property
    def is_fisheye(self) -> bool:
        return self.distortion_model == "equidistant"

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.D != 0))

    @property
    def P(self) -> np.ndarray:
        """(3,4) projection matrix world -> rectified px: K_rect [R | t]."""
        return self.K_rect @ np.hstack([self.R, self.t[:, None]])

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world metres."""
        return -self.R.T @ self.t

    def world_to_camera(self, X: np.ndarray) -> np.ndarray:
        """(...,3) world metres -> (...,3) camera-frame metres."""
        return np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def project_rectified(self, X: np.ndarray) -> np.ndarray:
        """(...,3) world metres -> (...,2) rectified pinhole px; NaN behind the camera."""
        Xc = self.world_to_camera(X)
        z = Xc[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (Xc[..., :2] / z) @ self.K_rect[:2, :2].T + self.K_rect[:2, 2]
        return np.where(z > 0, uv, np.nan)

    def project(self, X: np.ndarray) -> np.ndarray:
        """(...,3) world metres -> (...,2) raw (distorted) px; NaN behind the camera."""
        Xc = self.world_to_camera(X)
        shape = Xc.shape[:-1]
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = Xc[..., :2] / z[..., None]
        uv = self._distort_normalised(xn.reshape(-1, 2)).reshape(*shape, 2)
        return np.where((z > 0)[..., None], uv, np.nan)

    def distort_points(self, uv_rect: np.ndarray) -> np.ndarray:
        """(...,2) rectified px -> (...,2) raw px (inverse of undistort_points)."""
        uv_rect = np.asarray(uv_rect, dtype=np.float64)
        shape = uv_rect.shape[:-1]
        xn = (uv_rect.reshape(-1, 2) - self.K_rect[:2, 2]) @ np.linalg.inv(self.K_rect[:2, :2]).T
        return self._distort_normalised(xn).reshape(*shape, 2)

    def undistort_points(self, uv_raw: np.ndarray) -> np.ndarray:
        """(...,2) raw px -> (...,2) rectified pinhole px (K_rect)."""
        uv_raw = np.asarray(uv_raw, dtype=np.float64)
        shape = uv_raw.shape[:-1]
        pts = uv_raw.reshape(-1, 1, 2)
        if pts.shape[0] == 0:
            return uv_raw.copy()
        if not self.has_distortion and np.array_equal(self.K, self.K_rect):
            return uv_raw.copy()
        if self.is_fisheye:
            out = cv2.fisheye.undistortPoints(
                pts, self.K, self.D, R=np.eye(3), P=self.K_rect, criteria=_UNDISTORT_CRITERIA
            )
        else:
            out = cv2.undistortPoints(
                pts, self.K, self.D, R=np.eye(3), P=self.K_rect, criteria=_UNDISTORT_CRITERIA
            )
        return out.reshape(*shape, 2)

    def _distort_normalised(self, xn: np.ndarray) -> np.ndarray:
        """(M,2) normalised pinhole coordinates -> (M,2) raw px."""
        if xn.shape[0] == 0:
            return xn.copy()
        if not self.has_distortion:
            return xn @ self.K[:2, :2].T + self.K[:2, 2]
        finite = np.all(np.isfinite(xn), axis=1)
        out = np.full_like(xn, np.nan)
        pts = xn[finite].reshape(-1, 1, 2)
        if pts.shape[0]:
            if self.is_fisheye:
                uv = cv2.fisheye.distortPoints(pts, self.K, self.D)
            else:
                obj = np.concatenate([pts.reshape(-1, 2), np.ones((pts.shape[0], 1))], axis=1)
                uv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.K, self.D)
            out[finite] = uv.reshape(-1, 2)
        return out

    # ---- CameraInfo ------------------------------------------------------
    def to_camera_info(self) -> dict:
        """CameraInfo-shaped dict (ROS 2 field names) for the raw image."""
        P = np.hstack([self.K_rect, np.zeros((3, 1))])
        return {
            "width": self.width,
            "height": self.height,
            "distortion_model": self.distortion_model,
            "d": [float(x) for x in self.D],
            "k": [float(x) for x in self.K.ravel()],
            "r": [float(x) for x in np.eye(3).ravel()],
            "p": [float(x) for x in P.ravel()],
        }

    @classmethod
    def from_camera_info(cls, name: str, info: Mapping, R: np.ndarray, t: np.ndarray) -> Camera:
        """Build from a CameraInfo-shaped dict plus world->camera extrinsics (not in CameraInfo)."""
        P = _as_matrix(info["p"], (3, 4), f"camera {name!r} camera_info.p")
        K_rect = P[:, :3] if np.any(P[:, :3]) else None
        return cls(
            name=name,
            K=info["k"],
            R=R,
            t=t,
            width=info["width"],
            height=info["height"],
            distortion_model=info["distortion_model"] or "plumb_bob",
            D=info["d"],
            K_rect=K_rect,
        )

    # ---- MAEM authors' camera JSON ------------------------------------------
    @classmethod
    def from_maem_json(
        cls, data: Mapping, name: str | None = None, default_size: tuple[int, int] | None = None
    ) -> Camera:
        """Parse a MAEM/xrmocap camera JSON dict.

        Accepts ``extrinsic_r`` + ``extrinsic_t`` or a 4x4 ``extrinsic`` (world->camera), a 3x3 or
        3x4 ``intrinsic``, coefficients k1..k6 p1 p2 (missing = 0). A missing image size takes
        ``default_size`` (width, height) or, failing that, twice the principal point. An optional
        ``time_offset`` (s, this project's key; absent = 0) is kept.
        """
        cam_name = name or data.get("name") or "camera"
        where = f"camera {cam_name!r}"
        if "intrinsic" not in data:
            raise ValueError(f"{where}: missing 'intrinsic'")
        Kfull = np.asarray(data["intrinsic"], dtype=np.float64)
        if Kfull.shape not in ((3, 3), (3, 4)):
            raise ValueError(f"{where} intrinsic: expected 3x3 or 3x4, got {Kfull.shape}")
        K = Kfull[:, :3]
        if "extrinsic_r" in data and "extrinsic_t" in data:
            R, t = data["extrinsic_r"], data["extrinsic_t"]
        elif "extrinsic" in data:
            E = _as_matrix(data["extrinsic"], (4, 4), f"{where} extrinsic")
            R, t = E[:3, :3], E[:3, 3]
        else:
            raise ValueError(
                f"{where}: needs extrinsic_r + extrinsic_t or a 4x4 extrinsic (intrinsics "
                f"only: calibrate the rig first, maem-calibrate)"
            )
        if data.get("world2cam") is False:
            R = np.asarray(R, dtype=np.float64).T
            t = -R @ np.asarray(t, dtype=np.float64).ravel()
        coeff = {k: float(data.get(k, 0.0) or 0.0) for k in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")}
        model = _maem_distortion_model(data, coeff)
        if model == "equidistant":
            D = [coeff["k1"], coeff["k2"], coeff["k3"], coeff["k4"]]
        else:
            D = [coeff[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")]
        if "width" in data and "height" in data:
            width, height = int(data["width"]), int(data["height"])
        elif default_size is not None:
            width, height = default_size
        else:
            width, height = int(round(2 * K[0, 2])), int(round(2 * K[1, 2]))
        return cls(
            name=cam_name,
            K=K,
            R=R,
            t=t,
            width=width,
            height=height,
            distortion_model=model,
            D=np.asarray(D, float),
            time_offset=data.get("time_offset", 0.0),
        )

    def to_maem_json(self, extrinsics: bool = True) -> dict:
        """MAEM/xrmocap camera JSON dict (extrinsic_r + extrinsic_t, 3x3 intrinsic); without
        ``extrinsics`` the intrinsics only (read back by :meth:`Rig.load_intrinsics`)."""
        coeff = dict.fromkeys(("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"), 0.0)
        if self.is_fisheye:
            coeff.update(zip(("k1", "k2", "k3", "k4"), map(float, self.D)))
        else:
            coeff.update(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), map(float, self.D)))
        out = {
            "class_name": "FisheyeCameraParameter" if self.is_fisheye else "PinholeCameraParameter",
            "convention": "opencv",
            "name": self.name,
            "distortion_type": "fisheye" if self.is_fisheye else "opencv",
            "distortion_model": self.distortion_model,
            "extrinsic_r": self.R.tolist(),
            "extrinsic_t": self.t.tolist(),
            "intrinsic": self.K.tolist(),
            "width": self.width,
            "height": self.height,
            "world2cam": True,
            **coeff,
            **({"time_offset": self.time_offset} if self.time_offset else {}),
        }
        if not extrinsics:
            for key in ("extrinsic_r", "extrinsic_t", "world2cam"):
                del out[key]
        return out

    # ---- rig YAML entry ----------------------------------------------------
    def to_dict(self, extrinsics: bool = True) -> dict:
        """Rig YAML entry (``extrinsics`` False: no R, t; read by Rig.load_intrinsics)."""
        d = {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "distortion_model": self.distortion_model,
            "D": self.D.tolist(),
        }
        if not extrinsics:
            del d["R"], d["t"]
        if not np.array_equal(self.K_rect, self.K):
            d["K_rect"] = self.K_rect.tolist()
        if self.time_offset:
            d["time_offset"] = self.time_offset
        return d

    @classmethod
    def from_dict(cls, name: str, d: Mapping) -> Camera:
        missing = [k for k in ("width", "height", "K", "R", "t") if k not in d]
        if missing:
            raise ValueError(f"camera {name!r}: missing {', '.join(missing)}")
        return cls(
            name=name,
            K=d["K"],
            R=d["R"],
            t=d["t"],
            width=d["width"],
            height=d["height"],
            distortion_model=d.get("distortion_model", "plumb_bob"),
            D=d.get("D", []),
            K_rect=d.get("K_rect"),
            time_offset=d.get("time_offset", 0.0),
        )


def _maem_distortion_model(data: Mapping, coeff: Mapping[str, float]) -> str:
    explicit = data.get("distortion_model")
    if explicit:
        if explicit not in DISTORTION_MODELS:
            raise ValueError(f"camera distortion_model: unknown {explicit!r}")
        return explicit
    kind = str(data.get("distortion_type", data.get("type", "opencv"))).lower()
    if kind in ("fisheye", "equidistant", "kannala_brandt"):
        return "equidistant"
    if kind not in ("opencv", "pinhole", "plumb_bob", "rational_polynomial", ""):
        raise ValueError(f"camera distortion_type: unknown {kind!r}, expected fisheye or opencv")
    return "rational_polynomial" if any(coeff[k] for k in ("k4", "k5", "k6")) else "plumb_bob"


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3,3) cross-product matrix."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """(3,3) F with x_b^T F x_a = 0 for rectified homogeneous px x_a in a, x_b in b."""
    R_ab = cam_b.R @ cam_a.R.T
    t_ab = cam_b.t - R_ab @ cam_a.t
    E = skew(t_ab) @ R_ab
    F = np.linalg.inv(cam_b.K_rect).T @ E @ np.linalg.inv(cam_a.K_rect)
    return F / np.linalg.norm(F)


def _natural_key(s: str):
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]


class Rig:
    """An ordered set of named cameras. Camera index = position in this order."""

    def __init__(self, cameras: Sequence[Camera]):
        names = [c.name for c in cameras]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"rig: duplicate camera names {sorted(dup)}")
        self._cameras: dict[str, Camera] = {c.name: c for c in cameras}

    @property
    def names(self) -> list[str]:
        return list(self._cameras)

    @property
    def cameras(self) -> list[Camera]:
        return list(self._cameras.values())

    def __len__(self) -> int:
        return len(self._cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self._cameras.values())

    def __contains__(self, name: object) -> bool:
        return name in self._cameras

    def __getitem__(self, key: str | int) -> Camera:
        if isinstance(key, (int, np.integer)):
            return self.cameras[int(key)]
        try:
            return self._cameras[key]
        except KeyError:
            raise ValueError(f"rig: unknown camera {key!r}; known: {self.names}") from None

    def index(self, name: str) -> int:
        if name not in self._cameras:
            raise ValueError(f"rig: unknown camera {name!r}; known: {self.names}")
        return self.names.index(name)

    def fundamental_matrices(self) -> dict[tuple[int, int], np.ndarray]:
        """F for every ordered index pair (a, b), a < b: x_b^T F x_a = 0."""
        cams = self.cameras
        return {
            (a, b): fundamental_matrix(cams[a], cams[b])
            for a in range(len(cams))
            for b in range(a + 1, len(cams))
        }

    # ---- I/O ----------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """Load from a rig YAML, a folder of MAEM camera JSONs, a scene folder with cameras/, a
        Qualisys ``.qca.txt`` or a Pose2Sim ``Calib*.toml`` (core/geometry/rig_formats.py)."""
        p = Path(path)
        if p.is_dir():
            return cls.from_json_folder(p / "cameras" if (p / "cameras").is_dir() else p)
        if not p.exists():
            raise ValueError(f"rig {str(p)!r}: no such file or folder")
        if p.suffix.lower() in (".yaml", ".yml"):
            return cls.from_yaml(p)
        if is_calibration_file(p):
            return cls([Camera(**params) for params in read_calibration(p)])
        raise ValueError(
            f"rig {str(p)!r}: expected a .yaml file, a folder of camera JSONs, a "
            f"Qualisys .qca.txt or a Pose2Sim .toml"
        )

    @classmethod
    def from_json_folder(
        cls, folder: str | Path, default_size: tuple[int, int] | None = None, defaults: Mapping | None = None
    ) -> Rig:
        """Cameras named by JSON file stem, in natural order (camera_2 before camera_10);
        ``defaults``: keys a file may lack."""
        folder = Path(folder)
        files = sorted(folder.glob("*.json"), key=lambda f: _natural_key(f.stem))
        if not files:
            raise ValueError(f"rig {str(folder)!r}: no camera JSON files")
        cams = []
        for f in files:
            try:
                data = json.loads(f.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ValueError(f"rig camera file {str(f)!r}: unreadable JSON ({e})") from None
            if not isinstance(data, dict):
                raise ValueError(f"rig camera file {str(f)!r}: expected a JSON object")
            cams.append(
                Camera.from_maem_json({**(defaults or {}), **data}, name=f.stem, default_size=default_size)
            )
        return cls(cams)

    def to_json_folder(self, folder: str | Path, extrinsics: bool = True) -> None:
        """One MAEM camera JSON per camera (``extrinsics`` False: intrinsics only)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for cam in self:
            (folder / f"{cam.name}.json").write_text(json.dumps(cam.to_maem_json(extrinsics), indent=2))

    @classmethod
    def load_intrinsics(cls, path: str | Path) -> Rig:
        """K, distortion, image size and time_offset of every camera in any rig file or folder
        :meth:`load` reads, extrinsics optional (intrinsics-only camera JSONs or YAML entries
        are accepted) and discarded: every camera gets R = I, t = 0, a placeholder for a
        calibration to replace, never a pose."""
        p = Path(path)
        if p.is_dir() or p.suffix.lower() in (".yaml", ".yml"):
            placeholder = {
                "extrinsic_r": np.eye(3).tolist(),
                "extrinsic_t": [0.0, 0.0, 0.0],
                "R": np.eye(3).tolist(),
                "t": [0.0, 0.0, 0.0],
            }
            if p.is_dir():
                rig = cls.from_json_folder(
                    p / "cameras" if (p / "cameras").is_dir() else p, defaults=placeholder
                )
            else:
                rig = cls.from_yaml(p, defaults=placeholder)
        else:
            rig = cls.load(p)
        return cls([replace(c, R=np.eye(3), t=np.zeros(3)) for c in rig])

    @classmethod
    def from_yaml(cls, path: str | Path, defaults: Mapping | None = None) -> Rig:
        """A rig YAML (``cameras: {name: {...}}``); ``defaults``: keys an entry may lack."""
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as e:
            raise ValueError(f"rig {str(path)!r}: cannot read ({e.strerror})") from None
        if not isinstance(data, dict) or not isinstance(data.get("cameras"), dict) or not data["cameras"]:
            raise ValueError(f"rig {str(path)!r}: expected a mapping 'cameras: {{name: {{...}}}}'")
        bad = [str(n) for n, d in data["cameras"].items() if not isinstance(d, dict)]
        if bad:
            raise ValueError(f"rig {str(path)!r}: camera(s) {bad} are not mappings")
        return cls([Camera.from_dict(str(n), {**(defaults or {}), **d}) for n, d in data["cameras"].items()])

    def to_yaml(self, path: str | Path, extrinsics: bool = True) -> None:
        """Write the rig YAML (``extrinsics`` False: intrinsics only, for Rig.load_intrinsics)."""
        data = {"cameras": {c.name: c.to_dict(extrinsics) for c in self}}
        Path(path).write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
