"""Rig calibration from a planar board (ChArUco or checkerboard) seen by the cameras.

Conventions: board frame = OpenCV's (origin at the outer corner of the top-left square, x along
the columns, y along the rows, z into the board: the pattern faces -z), metres; inner corner id
``k`` lies at ``((k % cols + 1) * square, (k // cols + 1) * square, 0)`` (``cols`` x ``rows``
inner corners, as OpenCV's CharucoBoard numbers them). Camera extrinsics are world -> camera.

Steps (each a function here, pure computation on detections; reading images is the tool's):

1. :func:`detect_corners`: OpenCV's maintained detectors, ``cv2.aruco.CharucoDetector`` for
   ChArUco and ``cv2.findChessboardCornersSB`` for checkerboards.
2. :func:`calibrate_intrinsics`: ``cv2.calibrateCamera`` per camera (plumb_bob k1 k2 p1 p2 k3),
   views whose error is far above the others' dropped once and the calibration repeated.
3. :func:`calibrate_extrinsics`: frames where several cameras see the board. Per view a board
   pose (``cv2.solvePnP``, IPPE for planes); per camera pair the relative pose every shared
   frame implies, the consensus of the frames (frames that disagree are not simultaneous: a
   pair needs ``MIN_SHARED_FRAMES`` consistent ones); a maximum spanning tree over the
   consistent pairs gives the initial rig; then the project's bundle adjustment
   (core.calibrate.bundle) refines the cameras and every frame's board pose, with the board as
   a rigid object (its known layout fixes the scale). A checkerboard reads the same turned by
   180 degrees: each view takes the orientation that agrees with the rig.
4. World frame: the board of the first frame seen by two or more cameras, turned so that z
   points out of the pattern (lay the board flat on the floor, pattern up, in that frame to
   get z up); x along its columns.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .bundle import BundleOptions, BundleProblem, bundle_adjust

#: corners a view needs for the intrinsic calibration and for a board pose
MIN_CORNERS = 8
#: consistent simultaneous frames a camera pair needs to join the rig
MIN_SHARED_FRAMES = 2
#: two frames' relative poses agree when within these (deg, fraction of the baseline + m):
#: a far, small board's PnP pose is good to a few degrees; frames not taken together differ
#: by tens of degrees
AGREE_DEG, AGREE_REL, AGREE_M = 6.0, 0.1, 0.05
#: views whose RMS exceeds this many times the median view's are dropped once (intrinsics)
VIEW_OUTLIER_FACTOR = 3.0
#: bundle adjustment schedule for board corners (sub-pixel accurate): narrow losses, px
BOARD_SCHEDULE = (("cauchy", 4.0, 40), ("soft_l1", 1.0, 80))
#: intrinsics the one-run calibration refines in the joint bundle (k3 only when the per-camera
#: calibration freed it too): everything cv2.calibrateCamera estimates. Not OpenCV's own
#: cv2.calibrateMultiview (in the installed OpenCV 5.1.0): it starts from the same per-camera
#: calibrateCamera and keeps those intrinsics in its joint stage; on lab4's projected corners
#: (16 shared boards, 0.2 px noise, seeds 1 and 2) it left the principal points 2.5-8.4 px off,
#: exactly the per-camera values, and the relative rotations 1.1-1.2 deg off
JOINT_INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")

_SPEC_RE = {
    "charuco": re.compile(r"charuco:(\d+)x(\d+):([0-9.eE+-]+):([0-9.eE+-]+):(\w+)$"),
    "checkerboard": re.compile(r"checkerboard:(\d+)x(\d+):([0-9.eE+-]+)$"),
}
BOARD_SYNTAX = (
    "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (e.g. charuco:7x5:0.12:0.09:DICT_4X4_50)"
    " or checkerboard:COLSxROWS:SQUARE_M (COLSxROWS counts inner corners)"
)


@dataclass(frozen=True)
class BoardSpec:
    """A planar calibration board: ``cols`` x ``rows`` inner corners, ``square`` m; ChArUco
    boards also ``marker`` m and a cv2.aruco ``dictionary`` name (DICT_4X4_50 ...)."""

    kind: str
    cols: int
    rows: int
    square: float
    marker: float = 0.0
    dictionary: str = ""

    def __post_init__(self) -> None:
        if self.kind not in _SPEC_RE:
            raise ValueError(f"board: unknown kind {self.kind!r}, expected {BOARD_SYNTAX}")
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"board: needs at least 2x2 inner corners, got {self.cols}x{self.rows}")
        if not (np.isfinite(self.square) and self.square > 0):
            raise ValueError(f"board: square size {self.square} m is not positive")
        if self.kind == "charuco":
            if not 0 < self.marker < self.square:
                raise ValueError(
                    f"board: marker size {self.marker} m must lie in (0, square {self.square} m)"
                )
            if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(
                    f"board: unknown ArUco dictionary {self.dictionary!r} (cv2.aruco "
                    f"names such as DICT_4X4_50, DICT_5X5_100)"
                )

    @classmethod
    def parse(cls, text: str) -> BoardSpec:
        """``charuco:7x5:0.12:0.09:DICT_4X4_50`` or ``checkerboard:9x6:0.025``."""
        kind = text.split(":", 1)[0]
        m = _SPEC_RE.get(kind, _SPEC_RE["charuco"]).match(text.strip())
        if kind not in _SPEC_RE or m is None:
            raise ValueError(f"board {text!r}: expected {BOARD_SYNTAX}")
        g = m.groups()
        try:
            if kind == "charuco":
                return cls(kind, int(g[0]), int(g[1]), float(g[2]), float(g[3]), g[4])
            return cls(kind, int(g[0]), int(g[1]), float(g[2]))
        except ValueError as e:
            raise ValueError(f"board {text!r}: {str(e).removeprefix('board: ')}") from None

    def __str__(self) -> str:
        if self.kind == "charuco":
            return f"charuco:{self.cols}x{self.rows}:{self.square:g}:{self.marker:g}:{self.dictionary}"
        return f"checkerboard:{self.cols}x{self.rows}:{self.square:g}"

    @property
    def num_corners(self) -> int:
        return self.cols * self.rows

    @property
    def squares(self) -> tuple[int, int]:
        """Squares along x and y (inner corners + 1)."""
        return self.cols + 1, self.rows + 1

    def corners(self) -> np.ndarray:
        """(N,3) inner corners in the board frame, m (id order)."""
        k = np.arange(self.num_corners)
        return np.column_stack(
            [(k % self.cols + 1) * self.square, (k // self.cols + 1) * self.square, np.zeros(k.size)]
        )

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square, self.marker, dictionary)

    def orientations(self) -> list[np.ndarray]:
        """Id permutations under which a detector may report the board: a checkerboard also
        reads turned by 180 degrees (id k <-> N-1-k); a ChArUco board is unambiguous."""
        ids = np.arange(self.num_corners)
        return [ids] if self.kind == "charuco" else [ids, ids[::-1].copy()]


@dataclass
class Detection:
    """Board corners found in one image: ``ids`` (n,) into BoardSpec.corners, ``uv`` (n,2) raw px."""

    ids: np.ndarray
    uv: np.ndarray


class CornerDetector:
    """Finds the board's inner corners in grayscale images (one detector object reused)."""

    def __init__(self, spec: BoardSpec):
        self.spec = spec
        if spec.kind == "charuco":
            self._charuco = cv2.aruco.CharucoDetector(spec.charuco_board())

    def __call__(self, gray: np.ndarray) -> Detection | None:
        """Corners of ``gray`` (H,W) uint8, or None when fewer than MIN_CORNERS are found."""
        if self.spec.kind == "charuco":
            corners, ids, _, _ = self._charuco.detectBoard(gray)
            if ids is None or len(ids) < MIN_CORNERS:
                return None
            return Detection(ids.ravel().astype(np.int64), corners.reshape(-1, 2).astype(np.float64))
        # CALIB_CB_ACCURACY (an upsampled search) costs 3x the time for less than the
        # cornerSubPix refinement below gains on the sector-based corners
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCornersSB(gray, (self.spec.cols, self.spec.rows), flags=flags)
        if not found:
            return None
        grid = corners.reshape(self.spec.rows, self.spec.cols, 2)
        spacing = min(
            np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
            np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
        )
        half = int(np.clip(0.3 * spacing, 2, 8))  # the window stays inside one square
        corners = cv2.cornerSubPix(
            gray,
            corners.astype(np.float32),
            (half, half),
            (-1, -1),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
        )
        return Detection(np.arange(self.spec.num_corners), corners.reshape(-1, 2).astype(np.float64))


def detect_corners(gray: np.ndarray, spec: BoardSpec) -> Detection | None:
    """One-off :class:`CornerDetector` call (loops should keep a detector)."""
    return CornerDetector(spec)(gray)


@dataclass
class Intrinsics:
    """One camera's calibrated intrinsics: K (3,3) px, D (5,) plumb_bob, image size px, RMS
    reprojection error px over the ``views`` used (``dropped`` views left out as outliers) of
    cv2.calibrateCamera; ``joint``: K and D were then refined in the joint bundle."""

    K: np.ndarray
    D: np.ndarray
    width: int
    height: int
    rms: float
    views: int
    dropped: int = 0
    joint: bool = False


def calibrate_intrinsics(
    detections: list[Detection],
    spec: BoardSpec,
    size: tuple[int, int],
    camera: str = "camera",
    k3: bool = False,
) -> Intrinsics:
    """``cv2.calibrateCamera`` on one camera's board views (``size`` = (width, height) px):
    k1 k2 p1 p2, and k3 only with ``k3`` (a free k3 trades off against the focal length on
    the few views a board session gives; wide-angle lenses may need it)."""
    flags = 0 if k3 else cv2.CALIB_FIX_K3
    views = [d for d in detections if d is not None and len(d.ids) >= MIN_CORNERS]
    if len(views) < 3:
        raise ValueError(
            f"camera {camera!r}: the board was found in {len(views)} image(s); the "
            f"intrinsic calibration needs at least 3 (with {MIN_CORNERS}+ corners)"
        )
    model = spec.corners()

    def run(chosen: list[Detection]):
        obj = [model[d.ids].astype(np.float32) for d in chosen]
        img = [d.uv.astype(np.float32).reshape(-1, 1, 2) for d in chosen]
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
        per_view = [
            float(
                np.sqrt(
                    np.mean(
                        np.sum(
                            (cv2.projectPoints(o, r, t, K, D)[0].reshape(-1, 2) - i.reshape(-1, 2)) ** 2,
                            axis=1,
                        )
                    )
                )
            )
            for o, i, r, t in zip(obj, img, rvecs, tvecs)
        ]
        return float(rms), K, D.ravel(), np.asarray(per_view)

    rms, K, D, per_view = run(views)
    keep = per_view <= VIEW_OUTLIER_FACTOR * max(np.median(per_view), 0.2)
    dropped = int((~keep).sum())
    if dropped and keep.sum() >= 3:
        rms, K, D, per_view = run([v for v, k in zip(views, keep) if k])
    else:
        dropped = 0
    return Intrinsics(
        K,
        np.concatenate([D[:5], np.zeros(max(0, 5 - D.size))]),
        int(size[0]),
        int(size[1]),
        rms,
        len(views) - dropped,
        dropped,
    )


# ---- extrinsics ------------------------------------------------------------------------------
@dataclass
class _View:
    """One camera's detection in one frame with its board pose (board -> camera)."""

    camera: int
    frame: int
    ids: np.ndarray
    uv: np.ndarray  # (n,2) raw px
    uv_rect: np.ndarray  # (n,2) px, undistorted to the camera's K
    R: np.ndarray
    t: np.ndarray


@dataclass
class Extrinsics:
    """World -> camera R (C,3,3), t (C,3) m and intrinsics K (C,3,3) px, D (C,5) plumb_bob (the
    given ones, or refined jointly); per camera the reprojection errors of its inlier corners
    (px; in the undistorted image, or the raw one when the intrinsics were refined) and how many
    frames it shared; the board poses (board -> world) of the frames used; the camera pairs that
    joined the rig (a, b, frames)."""

    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    D: np.ndarray
    errors: list[np.ndarray]
    frames_per_camera: np.ndarray
    board_R: np.ndarray
    board_t: np.ndarray
    board_frames: list[int]
    edges: list[tuple[int, int, int]] = field(default_factory=list)


class NotSimultaneous(ValueError):
    """No camera pair saw the board in enough consistent shared frames: intrinsics only."""


def _board_pose(spec: BoardSpec, ids: np.ndarray, uv_rect: np.ndarray, K: np.ndarray):
    """Board -> camera (R, t) of one view by PnP on undistorted px (IPPE, planar), or None."""
    obj = spec.corners()[ids]
    ok, rvec, tvec = cv2.solvePnP(obj, uv_rect.reshape(-1, 1, 2), K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok or tvec[2, 0] <= 0:
        return None
    ok, rvec, tvec = cv2.solvePnP(
        obj,
        uv_rect.reshape(-1, 1, 2),
        K,
        None,
        rvec,
        tvec,
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    return (cv2.Rodrigues(rvec)[0], tvec.ravel()) if ok else None


def _views(
    spec: BoardSpec,
    detections: dict[tuple[int, int], Detection],
    cameras: list[tuple[np.ndarray, np.ndarray]],
) -> list[_View]:
    out = []
    for (c, f), det in sorted(detections.items()):
        if det is None or len(det.ids) < MIN_CORNERS:
            continue
        K, D = cameras[c]
        uv = cv2.undistortPoints(det.uv.reshape(-1, 1, 2), K, D, P=K).reshape(-1, 2)
        pose = _board_pose(spec, det.ids, uv, K)
        if pose is not None:
            out.append(_View(c, f, det.ids, det.uv, uv, *pose))
    return out


def _turned(spec: BoardSpec, view: _View, perm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The view's board pose if its corners are read with ids ``perm[ids]``: the board turned
    about its centre (a checkerboard's 180-degree ambiguity)."""
    if perm[0] == 0:
        return view.R, view.t
    centre = np.array([(spec.cols + 1) * spec.square / 2, (spec.rows + 1) * spec.square / 2, 0.0])
    F = np.diag([-1.0, -1.0, 1.0])
    return view.R @ F, view.t + 2.0 * view.R @ centre


def _agree(Ra, ta, Rb, tb) -> bool:
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec()))
    return angle <= AGREE_DEG and np.linalg.norm(ta - tb) <= AGREE_REL * np.linalg.norm(ta) + AGREE_M


def _pair_poses(spec: BoardSpec, views: list[_View], C: int):
    """{(a, b): (R_ba, t_ba, frames)}: per camera pair the relative pose (camera a -> camera b)
    the most shared frames agree on, averaged over them."""
    by_frame: dict[int, list[_View]] = {}
    for v in views:
        by_frame.setdefault(v.frame, []).append(v)
    cands: dict[tuple[int, int], list[tuple[int, np.ndarray, np.ndarray]]] = {}
    for frame, vs in by_frame.items():
        for va in vs:
            for vb in vs:
                if va.camera >= vb.camera:
                    continue
                for perm in spec.orientations():
                    Rb, tb = _turned(spec, vb, perm)
                    R = Rb @ va.R.T
                    cands.setdefault((va.camera, vb.camera), []).append((frame, R, tb - R @ va.t))
    out = {}
    for pair, cs in cands.items():
        best: list[tuple] = []
        for _, Ri, ti in cs:
            agree = [(f, R, t) for f, R, t in cs if _agree(R, t, Ri, ti)]
            if len({f for f, _, _ in agree}) > len({f for f, _, _ in best}):
                best = agree
        frames: dict = {}
        for f, R, t in best:  # one pose per frame
            frames.setdefault(f, (R, t))
        if len(frames) >= MIN_SHARED_FRAMES:
            Rs = Rotation.from_matrix(np.stack([R for R, _ in frames.values()]))
            out[pair] = (Rs.mean().as_matrix(), np.mean([t for _, t in frames.values()], axis=0), len(frames))
    return out


def _spanning_tree(pairs: dict, C: int, root: int):
    """Camera poses (world = root camera) along a maximum spanning tree of the pairs (weight =
    consistent shared frames); unreached cameras stay None."""
    R: list = [None] * C
    t: list = [None] * C
    R[root], t[root] = np.eye(3), np.zeros(3)
    edges: list[tuple] = []
    while True:
        best = None
        for (a, b), (Rba, tba, n) in pairs.items():
            if (R[a] is None) == (R[b] is None):
                continue
            if best is None or n > best[2]:
                best = (a, b, n, Rba, tba)
        if best is None:
            return R, t, edges
        a, b, n, Rba, tba = best
        if R[a] is not None:  # X_b = Rba X_a + tba
            R[b], t[b] = Rba @ R[a], Rba @ t[a] + tba
        else:
            R[a], t[a] = Rba.T @ R[b], Rba.T @ (t[b] - tba)
        edges.append((a, b, n))


def _frame_boards(spec: BoardSpec, views: list[_View], R: list, t: list):
    """Board -> world pose of every frame seen by 2+ cameras (from its view with the most
    corners) and every view of those frames with its ids in that board's orientation."""
    by_frame: dict[int, list[_View]] = {}
    for v in views:
        by_frame.setdefault(v.frame, []).append(v)
    boards, used = [], []
    for frame in sorted(by_frame):
        vs = by_frame[frame]
        if len(vs) < 2:
            continue
        anchor = max(vs, key=lambda v: len(v.ids))
        c = anchor.camera
        Rw, tw = R[c].T @ anchor.R, R[c].T @ (anchor.t - t[c])
        kept = []
        for v in vs:
            Rp, tp = R[v.camera] @ Rw, R[v.camera] @ tw + t[v.camera]  # predicted board pose
            errs: list[tuple[float, np.ndarray]] = []
            for perm in spec.orientations():
                Rv, tv = _turned(spec, v, perm)
                ang = np.linalg.norm(Rotation.from_matrix(Rv @ Rp.T).as_rotvec())
                rel = np.linalg.norm(tv - tp) / max(float(np.linalg.norm(tp)), 1e-9)
                errs.append((float(ang + rel), perm))
            err, perm = min(errs, key=lambda e: float(e[0]))
            if err < np.radians(10.0) + 0.1:  # a view far from its rig prediction is left out
                kept.append((v, perm[v.ids]))
        if len(kept) >= 2:
            boards.append((frame, Rw, tw))
            used.append(kept)
    return boards, used


def _bundle(
    spec: BoardSpec,
    cameras: list[tuple[np.ndarray, np.ndarray]],
    R: list,
    t: list,
    boards,
    used,
    root: int,
    intrinsics: tuple[str, ...],
):
    """The shared bundle adjustment with each frame's board as a rigid object: on the
    undistorted corners with the intrinsics fixed, or on the raw corners refining
    ``intrinsics`` (names of bundle_solver.INTRINSIC_NAMES) of every camera."""
    model = spec.corners()
    point_index: dict[tuple[int, int], int] = {}
    obs_cam, obs_pt, obs_uv = [], [], []
    for o, kept in enumerate(used):
        for v, ids in kept:
            for k, uv in zip(ids, v.uv if intrinsics else v.uv_rect):
                p = point_index.setdefault((o, int(k)), len(point_index))
                obs_cam.append(v.camera)
                obs_pt.append(p)
                obs_uv.append(uv)
    raw = bool(intrinsics)  # else: undistorted corners, an ideal pinhole
    keys = np.array(list(point_index), dtype=np.int64).reshape(-1, 2)
    oR = np.stack([b[1] for b in boards])
    ot = np.stack([b[2] for b in boards])
    prob = BundleProblem(
        K=np.stack([K for K, _ in cameras]),
        R=np.stack(R),
        t=np.stack(t),
        points=np.einsum("pij,pj->pi", oR[keys[:, 0]], model[keys[:, 1]]) + ot[keys[:, 0]],
        obs_camera=np.array(obs_cam),
        obs_point=np.array(obs_pt),
        obs_uv=np.array(obs_uv),
        point_object=keys[:, 0],
        model=model[keys[:, 1]],
        object_R=oR,
        object_t=ot,
        dist=np.stack([D for _, D in cameras]) if raw else np.zeros((len(cameras), 5)),
    )
    opts = BundleOptions(
        schedule=BOARD_SCHEDULE, fixed_cameras=(root,), outlier_px=2.0, intrinsics=intrinsics
    )
    return prob, bundle_adjust(prob, opts)


def _to_board_world(R: np.ndarray, t: np.ndarray, bR: np.ndarray, bt: np.ndarray):
    """Re-express cameras (R, t world -> camera) and boards (board -> world) in the frame of
    board 0 turned so that z points out of the pattern: x_new = A x_old + b."""
    A = np.diag([1.0, -1.0, -1.0]) @ bR[0].T
    b = -A @ bt[0]
    Rn = R @ A.T
    tn = t - np.einsum("cij,j->ci", Rn, b)
    return Rn, tn, A @ bR, bt @ A.T + b


def calibrate_extrinsics(
    spec: BoardSpec,
    detections: dict[tuple[int, int], Detection],
    cameras: list[tuple[np.ndarray, np.ndarray]],
    names: list[str],
    intrinsics: tuple[str, ...] = (),
) -> Extrinsics:
    """Extrinsics of cameras ``names`` (intrinsics ``cameras[c]`` = (K, D)) from
    ``detections[(camera index, frame)]`` (frames with the same index are simultaneous);
    with ``intrinsics`` (e.g. JOINT_INTRINSICS) those of every camera are refined too, from
    the start ``cameras`` (see the module docstring).

    Raises NotSimultaneous (message names the cameras) when some camera shares fewer than
    MIN_SHARED_FRAMES consistent frames with the others."""
    C = len(names)
    views = _views(spec, detections, cameras)
    pairs = _pair_poses(spec, views, C)
    if not pairs:
        raise NotSimultaneous(
            f"no camera pair saw the board in {MIN_SHARED_FRAMES}+ simultaneous frames that "
            f"agree (images taken one camera at a time?): extrinsics cannot be computed"
        )
    counts = np.bincount([v.camera for v in views], minlength=C)
    in_pairs = {c for pair in pairs for c in pair}
    root = max(in_pairs, key=lambda c: (counts[c], -c))
    R, t, edges = _spanning_tree(pairs, C, root)
    lonely = [names[c] for c in range(C) if R[c] is None]
    if lonely:
        raise NotSimultaneous(
            f"camera(s) {', '.join(lonely)} share fewer than {MIN_SHARED_FRAMES} "
            f"consistent simultaneous board frames with the others: extrinsics "
            f"cannot be computed for the whole rig"
        )
    boards, used = _frame_boards(spec, views, R, t)
    placed = {v.camera for kept in used for v, _ in kept}
    if len(placed) < C:
        raise NotSimultaneous(
            f"camera(s) {', '.join(names[c] for c in range(C) if c not in placed)} "
            f"have no board view that agrees with the initial rig: extrinsics "
            f"cannot be computed for the whole rig"
        )
    prob, res = _bundle(spec, cameras, R, t, boards, used, root, tuple(intrinsics))
    err = res.errors()
    ok = res.inliers & np.isfinite(err)
    errors = [err[ok & (prob.obs_camera == c)] for c in range(C)]
    frames = np.array([sum(1 for kept in used if any(v.camera == c for v, _ in kept)) for c in range(C)])
    Rn, tn, bR, bt = _to_board_world(res.R, res.t, res.object_R, res.object_t)
    K = res.K if intrinsics else np.stack([K for K, _ in cameras])
    D = res.dist if intrinsics else np.stack([D for _, D in cameras])
    return Extrinsics(
        Rn, tn, K, D, errors, frames, bR, bt, [b[0] for b in boards], [(a, b, n) for a, b, n in edges]
    )
