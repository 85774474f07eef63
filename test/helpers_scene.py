"""Constructed scenes shared by the unit tests: exact pinhole cameras (no distortion, K_rect = K)
on a ring around the court, people as rigid point sets (vertices and joints) standing or
walking, FrameDetections made by projecting them through the cameras -- so every expected
answer is known by construction -- and FrameDetections of random numbers for the wire and
validation tests. One factory per concept, options as keywords.

Also the authors' real SportCenter camera (distorted, from the shared calibration files) and
a zero-noise scene folder for maem-eval.

World frame: z up, metres, court centre at the origin. Image coordinates: rectified px.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from maem_ros.core.detections import FrameDetections
from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.sim import rigs as sim_rigs


#: the shared calibration files (the authors' real cameras); the copy next to the checkout
#: where /work/shared is not there
CALIB = Path("/work/shared/data/calibration")
if not CALIB.is_dir():
    CALIB = Path(__file__).resolve().parents[2] / "shared" / "data" / "calibration"
#: the real SportCenter camera's JSON, rounded: used where the calibration files are absent
SPORTCENTER_JSON = {
    "extrinsic_r": [[-0.99888, 0.00848, 0.04650], [-0.03786, 0.44538, -0.89454],
                    [-0.02830, -0.89530, -0.44456]],
    "extrinsic_t": [0.1923, 0.5309, 15.4859], "height": 992, "width": 1376,
    "intrinsic": [[828.52, 0.0, 676.65], [0.0, 842.40, 418.05], [0.0, 0.0, 1.0]],
    "k1": -0.34600, "k2": 0.12372, "p1": -0.00680, "p2": -0.00061, "k3": -0.01250, "name": "ace_0",
}


def sportcenter_camera(name: str = "ace_0") -> Camera:
    """The authors' real SportCenter camera (plumb_bob, strong barrel distortion, 1376 x 992)
    from CALIB, or SPORTCENTER_JSON where the file is absent; its R made orthonormal (the file's
    is only to 5 digits)."""
    path = CALIB / "sportcenter_fisheye_param_00.json"
    data = json.loads(path.read_text()) if path.is_file() else dict(SPORTCENTER_JSON)
    u, _, vt = np.linalg.svd(np.asarray(data["extrinsic_r"], float))
    data["extrinsic_r"] = (u @ vt).tolist()
    return Camera.from_maem_json(data, name=name)


def look_at(name: str, eye, target=(0.0, 0.0, 1.0), f: float = 1000.0,
            size: tuple[int, int] = (1280, 960), roll: float = 0.0,
            pixel_centre: bool = False) -> Camera:
    """A distortion-free camera ``name`` at ``eye`` (world m) looking at ``target``, image x
    horizontal (world z up) unless turned by ``roll`` rad about the optical axis, focal length
    ``f`` px; principal point at the image centre: (w/2, h/2), or with ``pixel_centre``
    ((w-1)/2, (h-1)/2), the centre in pixel-centre coordinates (the sim rigs' convention)."""
    R, t = sim_rigs.look_at(eye, target, roll)
    w, h = size
    cx, cy = ((w - 1) / 2, (h - 1) / 2) if pixel_centre else (w / 2, h / 2)
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
    return Camera(name=name, K=K, R=R, t=t, width=w, height=h)


def ring_rig(n: int = 4, radius: float = 12.0, height: float = 5.0, phase: float = 0.3,
             squash: float = 1.0, size: tuple[int, int] = (1280, 960), *, f: float = 1000.0,
             target: Sequence[float] = (0.0, 0.0, 1.0), angles: Sequence[float] | None = None,
             prefix: str = "cam", jitter_seed: int | None = None, aim_jitter: float = 2.0,
             pixel_centre: bool = False) -> Rig:
    """``n`` cameras ``<prefix>0``.. on a ring at ``height`` m, evenly spaced in angle from
    ``phase`` rad (or at the given ``angles``, rad), all looking at ``target`` (world m): a
    circle of ``radius`` m, or with ``squash`` < 1 an ellipse whose y semi-axis is
    ``squash * radius`` (a court's shape); images ``size``, focal length ``f`` px (see
    :func:`look_at` for ``pixel_centre``).

    With ``jitter_seed`` every camera is moved at random, as a real rig is set up: angle
    +-0.2 rad, height +-1 m, aim +-``aim_jitter`` m in x and y, roll +-0.05 rad (the
    calibration tests' rigs)."""
    ang = (np.linspace(0, 2 * np.pi, n, endpoint=False) + phase if angles is None
           else np.asarray(angles, float))
    rng = None if jitter_seed is None else np.random.default_rng(jitter_seed)
    aim0 = np.asarray(target, float)
    cams = []
    for i, a in enumerate(ang):
        z, aim, roll = height, aim0, 0.0
        if rng is not None:  # the draws in this order: the rigs of a seed stay the same
            a = a + rng.uniform(-0.2, 0.2)
            z = height + rng.uniform(-1, 1)
            aim = aim0 + [rng.uniform(-aim_jitter, aim_jitter),
                          rng.uniform(-aim_jitter, aim_jitter), 0.0]
            roll = rng.uniform(-0.05, 0.05)
        eye = (radius * np.cos(a), squash * radius * np.sin(a), z)
        cams.append(look_at(f"{prefix}{i}", eye, aim, f, size, roll, pixel_centre))
    return Rig(cams)


def two_facing_cameras() -> Rig:
    """Cameras ``a`` at (-10, 0, 3) and ``b`` at (10, 0, 3) m facing each other across the
    court (the epipolar and reprojection gate tests' pair)."""
    return Rig([look_at("a", (-10.0, 0.0, 3.0)), look_at("b", (10.0, 0.0, 3.0))])


#: ring_rig keywords of a court-shaped ring (an ellipse, HD images): the geometry the
#: triangulation, uncertainty and joint filter tests set their bounds on
COURT_RING = dict(phase=0.0, squash=0.8, size=(1920, 1080))
#: ring_rig keywords of the wire tests' rig (cameras camera_0.., 720p, 10 m out, 3 m up,
#: aimed at the origin)
WIRE_RING = dict(radius=10.0, height=3.0, phase=0.0, size=(1280, 720), f=800.0,
                 target=(0.0, 0.0, 0.0), prefix="camera_")
#: ring_rig keywords of the calibration tests' rigs (with jitter_seed: set up by hand)
CALIBRATION_RING = dict(phase=0.0, size=(1280, 720), pixel_centre=True)


class Pose:
    """One person at one instant: ``centre`` (3,), ``verts`` (V,3), ``joints`` (J,3), world m;
    unpacks and indexes as (centre, verts, joints)."""

    def __init__(self, centre: np.ndarray, verts: np.ndarray, joints: np.ndarray) -> None:
        self.centre, self.verts, self.joints = centre, verts, joints

    def __iter__(self):
        return iter((self.centre, self.verts, self.joints))

    def __getitem__(self, i: int) -> np.ndarray:
        return (self.centre, self.verts, self.joints)[i]


class Person:
    """A rigid body: ``num_vertices`` surface-ish vertices and ``num_joints`` joints drawn
    (from ``seed``) in a box around a centre at 0.9 m height, the centre at ``p0`` + ``v`` t
    (x, y in m and m/s); ``joints_seed`` draws the joints apart (another pose, same mesh)."""

    def __init__(self, p0: Sequence[float], seed: int, num_vertices: int = 300,
                 num_joints: int = 24, *, v: Sequence[float] = (0.0, 0.0),
                 joints_seed: int | None = None, fps: float = 30.0) -> None:
        rng = np.random.default_rng(seed)
        self.p0, self.v, self.fps = np.array([*p0, 0.9]), np.array([*v, 0.0]), fps
        self.verts = rng.uniform(-1, 1, (num_vertices, 3)) * [0.25, 0.15, 0.9]
        self.joints = rng.uniform(-1, 1, (num_joints, 3)) * [0.2, 0.12, 0.85]
        if joints_seed is not None:
            self.joints = np.random.default_rng(joints_seed).uniform(
                -1, 1, (num_joints, 3)) * [0.2, 0.12, 0.85]

    def at(self, f: int = 0) -> Pose:
        """The pose at frame ``f`` (time f / fps s)."""
        c = self.p0 + self.v * f / self.fps
        return Pose(c, self.verts + c, self.joints + c)


def people(n: int, joints: int, seed: int = 0) -> np.ndarray:
    """(n, joints, 3) world m: n people anywhere on an 8 x 6 m court, 0.2-1.8 m high, joints
    scattered 0.3 m around each (no body shape: the triangulation tests' points)."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-4, -3, 0.2], [4, 3, 1.8], (n, 1, 3)) + rng.normal(scale=0.3, size=(n, joints, 3))


def cluster(*members: tuple[int, int]) -> SimpleNamespace:
    """A cluster (the association's output) of (camera index, detection index) members."""
    return SimpleNamespace(members=np.array(members, dtype=np.int64).reshape(-1, 2))


def project_detections(cam: Camera, joints: np.ndarray, verts: np.ndarray | None = None, *,
                       centres: np.ndarray | None = None, kpts3d_world: np.ndarray | None = None,
                       scores: float | Sequence[float] | np.ndarray = 0.95, stamp_ns: int = 0,
                       noise_px: float = 0.0, rng: np.random.Generator | None = None
                       ) -> FrameDetections:
    """Camera ``cam``'s detections of P people, in the given order.

    joints (P,J,3) world m -> kpts2d (P,J,2) rectified px, plus N(0, ``noise_px``) noise from
    ``rng``; kpts3d (P,J,3) camera-frame m of ``kpts3d_world`` (default: the joints); verts
    (P,V,3) world m -> verts2d (P,V,2) float32, (P,0,2) without. bbox: centred on the projected
    ``centres`` (P,3) world m with half the projected vertices' extent (an exact detector's box
    around a body), else the extent of the (noisy) keypoints.
    """
    joints = np.asarray(joints, float)
    P, J = joints.shape[:2]
    kp = cam.project_rectified(joints)
    if noise_px:
        kp = kp + (rng or np.random.default_rng()).normal(scale=noise_px, size=kp.shape)
    uv = (cam.project_rectified(np.asarray(verts, float)) if verts is not None
          else np.zeros((P, 0, 2)))
    if centres is not None:
        half = 0.5 * (uv.max(1) - uv.min(1))
        # one centre at a time: the rounding of a single point's projection (a stacked
        # product rounds differently), which the constructed scenes were made with
        c = np.stack([cam.project_rectified(x) for x in np.asarray(centres, float)])
        bboxes = np.concatenate([c - half, c + half], 1)
    else:
        bboxes = np.concatenate([kp.min(1), kp.max(1)], 1)
    kp3d = cam.world_to_camera(joints if kpts3d_world is None else np.asarray(kpts3d_world, float))
    sc = np.broadcast_to(np.asarray(scores, float), (P,)).copy()
    return FrameDetections(cam.name, stamp_ns, bboxes, sc, kp, kp3d, uv.astype(np.float32))


def project_frames(rig: Rig, joints: np.ndarray, verts: np.ndarray | None = None,
                   rng: np.random.Generator | None = None, **kw) -> dict[str, FrameDetections]:
    """Every camera of ``rig`` sees every person (detection index = person index):
    :func:`project_detections` per camera, in rig order, drawing noise from one ``rng``."""
    return {cam.name: project_detections(cam, joints, verts, rng=rng, **kw) for cam in rig}


def pose_frames(rig: Rig, rows: dict[str, list[tuple]], *, scores: dict[str, Sequence[float]]
                | None = None, shuffle_seed: int | None = None, stamp_ns: int = 0,
                empty_shape: tuple[int, int] | None = None
                ) -> tuple[dict[str, FrameDetections], dict[str, list[Any]]]:
    """Exact detections of given people per camera: ``rows[cam]`` lists the camera's detections
    as (Pose, kpts3d_world (J,3) world m or None for the pose's own joints[, id]); the box is
    centred on the projected pose centre (:func:`project_detections`). ``scores[cam]``: per
    row (default 0.95); ``shuffle_seed``: each camera's rows in random order; ``empty_shape``:
    (J, V) of a camera without rows (default: the rows'). Returns (frames, ids) with ids[cam]
    the id (None without) of each detection row, in frame order."""
    frames, ids = {}, {}
    rng = np.random.default_rng(shuffle_seed)
    shape = empty_shape or next((len(r[0].joints), len(r[0].verts))
                                for items in rows.values() for r in items)
    for name, items in rows.items():
        order = rng.permutation(len(items)) if shuffle_seed is not None else np.arange(len(items))
        ids[name] = [items[o][2] if len(items[o]) > 2 else None for o in order]
        if not len(items):
            frames[name] = FrameDetections.empty(name, stamp_ns, *shape)
            continue
        got = [items[o] for o in order]
        sc = 0.95 if scores is None or name not in scores else np.asarray(scores[name], float)[order]
        frames[name] = project_detections(
            rig[name], np.stack([p.joints for p, *_ in got]), np.stack([p.verts for p, *_ in got]),
            centres=np.stack([p.centre for p, *_ in got]), scores=sc, stamp_ns=stamp_ns,
            kpts3d_world=np.stack([p.joints if k3 is None else k3 for p, k3, *_ in got]))
    return frames, ids


#: stamp of frame 0 of a walking-people sequence (walk_frame), ns
T0_NS = 1_700_000_000_000_000_000


def walk_frame(rig: Rig, people: Sequence[Person], f: int, *, seen=None, kpts3d_of=None,
               stamp_ns: int | None = None) -> tuple[dict[str, FrameDetections], dict[str, list[Any]]]:
    """Exact detections of walking ``people`` at frame ``f`` (:func:`pose_frames`), stamped
    T0_NS + f / fps (``stamp_ns`` instead if given); ``seen(cam, k)`` -> bool: whether camera
    cam detects person k (default all); ``kpts3d_of(cam, k)`` -> the person whose 3D pose that
    detection carries (default k). Returns (frames, person index of each row per camera)."""
    fps = people[0].fps if people else 30.0
    stamp = T0_NS + int(round(f * 1e9 / fps)) if stamp_ns is None else stamp_ns
    poses = [p.at(f) for p in people]
    rows = {cam.name: [(poses[k], poses[kpts3d_of(cam.name, k)].joints if kpts3d_of else None, k)
                       for k in range(len(people)) if seen is None or seen(cam.name, k)]
            for cam in rig}
    shape = (len(people[0].joints), len(people[0].verts)) if people else (0, 0)
    return pose_frames(rig, rows, stamp_ns=stamp, empty_shape=shape)


def random_detections(n: int = 3, j: int = 4, v: int = 50, seed: int = 0, *,
                      camera: str = "cam0", stamp_ns: int = 1,
                      xy: tuple[float, float] = (0.0, 1000.0),
                      box: float | tuple[float, float] = 50.0, score: float | None = None,
                      kpts: tuple[float, float] = (0.0, 1000.0),
                      verts: tuple[float, float] = (0.0, 1000.0), **fields: Any) -> FrameDetections:
    """``n`` detections of random numbers (no geometry: for the wire and validation tests),
    ``j`` keypoints and ``v`` vertices each, from ``seed``: box corners uniform in ``xy`` px,
    box sides ``box`` px (a (lo, hi) range: uniform), scores ``score`` (None: uniform in
    [0, 1)), kpts2d uniform in ``kpts`` px, kpts3d N(0, 1) m, verts2d uniform in ``verts`` px.
    ``fields``: FrameDetections fields given instead (``bboxes`` given: no box drawn). Drawn
    in that order, so a seed's detections stay the same."""
    rng = np.random.default_rng(seed)
    if "bboxes" not in fields:
        lo = rng.uniform(*xy, (n, 2))
        wh = rng.uniform(*box, (n, 2)) if isinstance(box, tuple) else box
        fields["bboxes"] = np.concatenate([lo, lo + wh], 1)
    drawn: dict[str, Any] = dict(
        camera=camera, stamp_ns=stamp_ns,
        scores=rng.uniform(0, 1, n) if score is None else np.full(n, score),
        kpts2d=rng.uniform(*kpts, (n, j, 2)), kpts3d=rng.normal(0, 1, (n, j, 3)),
        verts2d=rng.uniform(*verts, (n, v, 2)))
    return FrameDetections(**{**drawn, **fields})


def exact_scene(root: Path, frames: int = 4, people: int = 3, vertices: int = 300) -> Any:
    """A scene folder (core.interchange.SceneFolder at ``root``, as maem-sim writes one) of a
    hand-built zero-noise scene on the humanm3_4 rig: ``people`` distinct random bodies (70
    MHR joints + ``vertices`` vertices, world m) walking slowly, exact raw-px estimator outputs
    per camera and frame, and their SportCenter-13 ground truth."""
    from maem_ros.core.interchange import SceneFolder
    from maem_ros.core.skeleton import SPORTCENTER_13
    from maem_ros.sim.rigs import build_rig
    rig = build_rig("humanm3_4")
    rng = np.random.default_rng(0)
    box = np.array([0.5, 0.35, 1.8])
    bodies = [rng.uniform(-0.5, 0.5, (70 + vertices, 3)) * box + [0, 0, 0.9] for _ in range(people)]
    starts = np.array([[-6.0, 1.0, 0.0], [2.0, 4.0, 0.0], [5.0, -4.0, 0.0],
                       [-2.0, -5.0, 0.0]])[:people]
    folder = SceneFolder.create(root, rig,
                                {"fps": 30.0, "start_stamp_ns": 0, "num_frames": frames})
    gt = np.zeros((frames, people, 13, 3))
    for f in range(frames):
        world = [b + s + [0.05 * f, 0.02 * f, 0] for b, s in zip(bodies, starts)]
        gt[f] = SPORTCENTER_13.select(np.stack([w[:70] for w in world]))
        for cam in rig:
            outputs = []
            for w in world:
                raw = cam.project(w)
                outputs.append({"bbox": np.concatenate([raw[70:].min(0), raw[70:].max(0)]),
                                "bbox_score": 0.95,
                                "pred_keypoints_3d": cam.world_to_camera(w[:70]),
                                "pred_keypoints_2d": raw[:70], "pred_keypoints_2d_verts": raw[70:]})
            folder.write_outputs(cam.name, f, outputs)
    folder.write_gt(gt, np.ones(gt.shape[:3], bool))
    return folder
