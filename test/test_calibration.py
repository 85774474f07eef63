"""Calibration readers: Qualisys .qca.txt (the real Pose2Sim Demo_MultiPerson numbers) and Pose2Sim TOML."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from maem_ros.core.geometry.rig_formats import read_pose2sim_toml, read_qualisys, rotate_view
from maem_ros.core.geometry.camera import Camera, Rig

# Two cameras of Pose2Sim/Demo_MultiPerson/calibration/Calib.qca.txt (pose2sim 0.10.49), verbatim
_CAM01 = """<camera active="1" avg-residual="0.402000" model="none" point-count="999999999" serial="cam01" viewrotation="{rot}">
      <fov_marker bottom="1919" left="0" right="1087" top="0"/>
      <fov_video bottom="1919" left="0" right="1087" top="0"/>
      <transform r11="0.5536380477336265" r12="0.8046719867383512" r13="0.2144479094331626" r21="-0.4345300743838753" r22="0.05946489349975602" r23="0.8986921279821063" r31="0.7104002579937896" r32="-0.5907342212870501" r33="0.3825762057979294" x="1460.2323709212087" y="-1909.1590482454608" z="1896.5058524092062"/>
      <intrinsic centerPointU="34110.316406" centerPointV="60680.792969" focalLengthU="107599.671875" focalLengthV="107588.828125" focallength="9.314096596679686" radialDistortion1="-0.046183" radialDistortion2="0.139983" radialDistortion3="0.000000" sensorMaxU="69568" sensorMaxV="122816" sensorMinU="0.000000" sensorMinV="0.000000" skew="0.000000" tangentalDistortion1="0.000608" tangentalDistortion2="0.00069"/>
    </camera>"""
_CAM03 = """<camera active="1" avg-residual="0.450323" model="none" point-count="999999999" serial="cam03" viewrotation="0">
      <fov_video bottom="1919" left="0" right="1087" top="0"/>
      <transform r11="-0.740641130147863" r12="-0.6704153360235378" r13="-0.044654154988568895" r21="0.25251118212268814" r22="-0.3393170985114385" r23="0.9061467925015139" r31="-0.6226466246887545" r32="0.6598539110153292" r33="0.4205995683324882" x="-3216.86586729648" y="2231.1786368869416" z="2088.19103027083"/>
      <intrinsic centerPointU="32845.335938" centerPointV="61120.328125" focalLengthU="107622.296875" focalLengthV="107616.632813" focallength="9.316055073242188" radialDistortion1="-0.046705" radialDistortion2="0.137622" radialDistortion3="0.000000" sensorMaxU="69568" sensorMaxV="122816" sensorMinU="0.000000" sensorMinV="0.000000" skew="0.000000" tangentalDistortion1="-0.000542" tangentalDistortion2="-0.000517"/>
    </camera>"""


def _qca(tmp_path, *cameras: str, name: str = "Calib.qca.txt"):
    path = tmp_path / name
    path.write_text("<?xml version='1.0' encoding='ASCII'?>\n<calibration><cameras>\n"
                    + "\n".join(cameras) + "\n</cameras></calibration>\n")
    return path


def _qtm_project(X: np.ndarray, xml_numbers: dict) -> np.ndarray:
    """Independent pinhole + Brown model written from the QTM numbers: the camera frame of QTM
    (r_ij by row applied to X - position) looks along -z with y up."""
    M = np.array(xml_numbers["r"]).reshape(3, 3)
    xq = (X - np.array(xml_numbers["pos"]) / 1000.0) @ M.T
    x, y = xq[..., 0] / -xq[..., 2], -xq[..., 1] / -xq[..., 2]
    k1, k2, p1, p2 = np.array(xml_numbers["dist"]) / 64.0
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    fx, fy, cx, cy = np.array(xml_numbers["f_c"]) / 64.0
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


CAM01_NUMBERS = {
    "r": [0.5536380477336265, 0.8046719867383512, 0.2144479094331626, -0.4345300743838753,
          0.05946489349975602, 0.8986921279821063, 0.7104002579937896, -0.5907342212870501,
          0.3825762057979294],
    "pos": [1460.2323709212087, -1909.1590482454608, 1896.5058524092062],
    "dist": [-0.046183, 0.139983, 0.000608, 0.00069],
    "f_c": [107599.671875, 107588.828125, 34110.316406, 60680.792969],
}


def test_qualisys_real_numbers(tmp_path):
    cams = Rig.load(_qca(tmp_path, _CAM03.replace("cam03", "cam03"), _CAM01.format(rot=0))).cameras
    assert [c.name for c in cams] == ["cam01", "cam03"]  # natural order of serials
    c = cams[0]
    assert (c.width, c.height) == (1088, 1920)  # portrait, fov_video right/bottom + 1
    np.testing.assert_allclose(c.K, [[107599.671875 / 64, 0, 34110.316406 / 64],
                                     [0, 107588.828125 / 64, 60680.792969 / 64], [0, 0, 1]])
    assert c.K[0, 0] == pytest.approx(1681.24, abs=0.01)
    np.testing.assert_allclose(c.D, np.array([-0.046183, 0.139983, 0.000608, 0.00069, 0.0]) / 64)
    np.testing.assert_allclose(c.center, [1.4602323709212087, -1.9091590482454608, 1.8965058524092062])
    # looking down onto the treadmill (world z up): 15-30 degrees below the horizon
    optical_axis = c.R[2]
    assert 15 < np.degrees(np.arcsin(-optical_axis[2])) < 30
    # an independent projection from the QTM numbers agrees, with distortion, to 1e-6 px
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], size=(50, 3))
    np.testing.assert_allclose(c.project(X), _qtm_project(X, CAM01_NUMBERS), atol=1e-6)
    uv = c.project(np.zeros(3))
    assert 0 < uv[0] < c.width and 0 < uv[1] < c.height  # the world origin is in view


def test_qualisys_cameras_see_one_volume(tmp_path):
    """The two real cameras' optical axes pass within 0.5 m of each other ~3-4 m away."""
    c1, c3 = Rig.load(_qca(tmp_path, _CAM01.format(rot=0), _CAM03))
    o1, d1, o3, d3 = c1.center, c1.R[2], c3.center, c3.R[2]
    # closest points of the two axes
    A = np.stack([d1, -d3], axis=1)
    s, t = np.linalg.lstsq(A, o3 - o1, rcond=None)[0]
    p1, p3 = o1 + s * d1, o3 + t * d3
    assert np.linalg.norm(p1 - p3) < 0.5
    assert 3.0 < s < 4.5 and 3.0 < t < 4.5


@pytest.mark.parametrize("degrees", [90, 180, 270])
def test_viewrotation_rotates_the_image(tmp_path, degrees):
    """A viewrotation of d degrees: every pixel of the unrotated camera, rotated clockwise by d
    in its image, is where the rotated camera projects the point (distortion included)."""
    c0 = Rig.load(_qca(tmp_path, _CAM01.format(rot=0), name="a.qca.txt"))[0]
    cr = Rig.load(_qca(tmp_path, _CAM01.format(rot=degrees), name="b.qca.txt"))[0]
    X = np.random.default_rng(1).uniform([-1, -1, 0], [1, 1, 2], size=(40, 3))
    uv = c0.project(X)
    w, h = c0.width, c0.height
    for _ in range(degrees // 90):  # clockwise quarter turn: (u, v) -> (h-1-v, u)
        uv = np.stack([h - 1 - uv[:, 1], uv[:, 0]], axis=1)
        w, h = h, w
    assert (cr.width, cr.height) == (w, h)
    np.testing.assert_allclose(cr.project(X), uv, atol=1e-6)
    np.testing.assert_allclose(cr.center, c0.center, atol=1e-12)


def test_rotate_view_rejects_odd_angles():
    with pytest.raises(ValueError, match="viewrotation"):
        rotate_view(np.eye(3), np.zeros(4), np.eye(3), np.zeros(3), (10, 10), 45)


def test_qualisys_bad_input(tmp_path):
    with pytest.raises(ValueError, match="not valid XML"):
        read_qualisys(_qca(tmp_path, "<camera serial='x'"))
    bad = _CAM01.format(rot=0).replace('focalLengthU="107599.671875"', 'focalLengthU="abc"')
    with pytest.raises(ValueError, match="'cam01'.*focalLengthU"):
        read_qualisys(_qca(tmp_path, bad))
    with pytest.raises(ValueError, match="no <intrinsic> element"):
        read_qualisys(_qca(tmp_path, _CAM03.split("<transform")[0] + "</camera>"))
    with pytest.raises(ValueError, match="no <cameras><camera>"):
        read_qualisys(_qca(tmp_path))


def _pose2sim_toml(cams: list[Camera]) -> str:
    """What Pose2Sim's toml_write writes (Rodrigues rotation, world -> camera)."""
    out = []
    for c in cams:
        r = cv2.Rodrigues(c.R)[0].ravel()
        out.append(f'[{c.name}]\nname = "{c.name}"\nsize = [ {c.width}.0, {c.height}.0]\n'
                   f"matrix = [ [ {c.K[0, 0]}, 0.0, {c.K[0, 2]}], [ 0.0, {c.K[1, 1]}, {c.K[1, 2]}], "
                   f"[ 0.0, 0.0, 1.0]]\ndistortions = [ {c.D[0]}, {c.D[1]}, {c.D[2]}, {c.D[3]}]\n"
                   f"rotation = [ {r[0]}, {r[1]}, {r[2]}]\n"
                   f"translation = [ {c.t[0]}, {c.t[1]}, {c.t[2]}]\nfisheye = false\n\n")
    return "".join(out) + "[metadata]\nadjusted = false\nerror = 0.0\n"


def test_pose2sim_toml_matches_the_qualisys_conversion(tmp_path):
    cams = Rig.load(_qca(tmp_path, _CAM01.format(rot=0), _CAM03)).cameras
    path = tmp_path / "Calib_qualisys.toml"
    path.write_text(_pose2sim_toml(cams))
    rig = Rig.load(path)  # rig loading dispatches on the file name
    assert rig.names == ["cam01", "cam03"]
    X = np.random.default_rng(2).uniform([-1, -1, 0], [1, 1, 2], size=(30, 3))
    for a, b in zip(cams, rig):
        np.testing.assert_allclose(b.project(X), a.project(X), atol=1e-6)
        assert (b.width, b.height) == (a.width, a.height)


def test_pose2sim_toml_bad_input(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text('[cam1]\nname = "cam1"\nsize = [ 10.0, 10.0]\n')
    with pytest.raises(ValueError, match="'cam1': missing matrix, distortions, rotation, translation"):
        read_pose2sim_toml(path)
    path.write_text("[cam1\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        read_pose2sim_toml(path)
    path.write_text("[metadata]\nerror = 0.0\n")
    with pytest.raises(ValueError, match="no camera tables"):
        read_pose2sim_toml(path)


def test_rig_load_names_what_it_reads(tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text("x")
    with pytest.raises(ValueError, match="Qualisys .qca.txt or a Pose2Sim .toml"):
        Rig.load(path)


def test_real_qualisys_file(pose2sim_demo):
    """The whole real file: four portrait cameras 3.3-3.8 m from a common point, fx ~1675 px."""
    rig = Rig.load(pose2sim_demo / "calibration" / "Calib.qca.txt")
    assert rig.names == ["cam01", "cam02", "cam03", "cam04"]
    centres = np.stack([c.center for c in rig])
    axes = np.stack([c.R[2] for c in rig])
    # least-squares point closest to all four optical axes
    A = sum(np.eye(3) - np.outer(d, d) for d in axes)
    b = sum((np.eye(3) - np.outer(d, d)) @ o for d, o in zip(axes, centres))
    p = np.linalg.solve(A, b)
    dist = np.linalg.norm(centres - p, axis=1)
    assert np.all((dist > 3.0) & (dist < 4.2)), dist
    for c in rig:
        assert (c.width, c.height) == (1088, 1920)
        assert 1650 < c.K[0, 0] < 1700
        assert c.world_to_camera(p)[2] > 0


def test_pose2sim_toml_writer_round_trips(tmp_path):
    """write_pose2sim_toml -> the project's reader: the same cameras (k3 kept when non-zero, a
    fisheye and a rational_polynomial camera too), in the Pose2Sim/anipose layout."""
    from maem_ros.core.geometry.rig_formats import write_pose2sim_toml
    from maem_ros.sim.rigs import build_rig
    cams = build_rig("sportcenter6").cameras[:2] + build_rig("humanm3_3").cameras[:1]
    cams[2].name = "pinhole"
    cams.append(Camera("fish eye", [[300.0, 0, 320], [0, 301, 240], [0, 0, 1]], cams[0].R, [1.0, 2, 3],
                       640, 480, "equidistant", [0.1, -0.02, 0.003, -0.0004], time_offset=0.02))
    cams.append(Camera("rational", cams[2].K, cams[2].R, cams[2].t, 2048, 1536,
                       "rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002, 0.05, 0.0, 0.01]))
    path = tmp_path / "Calib.toml"
    write_pose2sim_toml(path, cams, error_px=0.31)
    back = Rig.load(path).cameras
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(cams, back):
        assert (b.width, b.height, b.distortion_model) == (a.width, a.height, a.distortion_model)
        np.testing.assert_array_equal(b.K, a.K)
        np.testing.assert_array_equal(b.D, a.D)
        np.testing.assert_array_equal(b.t, a.t)
        np.testing.assert_allclose(b.R, a.R, atol=1e-14)  # through Rodrigues
        assert b.time_offset == a.time_offset
    text = path.read_text()
    import tomllib
    data = tomllib.loads(text)
    assert data["metadata"] == {"adjusted": False, "error": 0.31}
    first = data[cams[0].name]
    assert set(first) == {"name", "size", "matrix", "distortions", "rotation", "translation",
                          "fisheye"}
    assert first["fisheye"] is False and len(first["distortions"]) == 5  # k3 != 0 in sportcenter6
    assert len(data["pinhole"]["distortions"]) == 4  # humanm3: pinhole, k1 k2 p1 p2 = 0
    assert data["fish eye"]["fisheye"] is True


def test_pose2sim_toml_writer_bad_input(tmp_path):
    from maem_ros.core.geometry.rig_formats import write_pose2sim_toml
    from maem_ros.sim.rigs import build_rig
    cam = build_rig("humanm3_3")[0]
    cam.name = "metadata"
    with pytest.raises(ValueError, match="'metadata' clashes"):
        write_pose2sim_toml(tmp_path / "Calib.toml", [cam])
    cam.name = "twice"
    with pytest.raises(ValueError, match="duplicate camera names"):
        write_pose2sim_toml(tmp_path / "Calib.toml", [cam, cam])
