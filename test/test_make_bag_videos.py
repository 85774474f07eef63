"""maem-make-bag --videos: one video per camera -> image_raw/compressed + camera_info, read back."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros import bagio
from maem_ros.tools.bags.make_bag import DEFAULT_START_NS, main, stamp_ns

W, H, NFRAMES, FPS = 64, 48, 6, 25.0


def frame_image(cam: int, k: int) -> np.ndarray:
    """A frame that says which camera and frame it is: grey level by frame, a bar by camera."""
    img = np.full((H, W, 3), 30 + 30 * k, np.uint8)
    img[:, 8 * cam:8 * cam + 16] = 255
    return img


def write_video(path: Path, cam: int, frames: int = NFRAMES, size=(W, H)) -> None:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, size)
    assert vw.isOpened()
    for k in range(frames):
        vw.write(cv2.resize(frame_image(cam, k), size))
    vw.release()


@pytest.fixture
def videos(tmp_path: Path) -> Path:
    K = [[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]
    rig = Rig([Camera("cam01", K, np.eye(3), [0, 0, 3], W, H),
               Camera("cam02", K, np.eye(3), [0.5, 0, 3], W, H, D=[0.01, 0, 0, 0, 0])])
    rig.to_yaml(tmp_path / "rig.yaml")
    (tmp_path / "videos").mkdir()
    write_video(tmp_path / "videos" / "cam01.avi", 0)
    write_video(tmp_path / "videos" / "cam02.avi", 1, frames=NFRAMES - 1)  # one frame short
    write_video(tmp_path / "videos" / "lobby.avi", 2)  # no calibration: skipped
    return tmp_path


def test_video_bag_round_trip(videos, capsys):
    out = videos / "bag"
    code = main([str(out), "--videos", str(videos / "videos"), "--rig", str(videos / "rig.yaml"),
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "lobby" in err and "no calibration" in err
    assert "missing video frame of camera cam02" in err
    info = bagio.bag_info(out)
    rig = Rig.load(videos / "rig.yaml")
    for c, cam in enumerate(rig.names):
        msgs = list(bagio.read_messages(out, [f"/{cam}/image_raw/compressed"]))
        n = NFRAMES if cam == "cam01" else NFRAMES - 1
        assert len(msgs) == n
        for k, m in enumerate(msgs):
            # the videos' own frame rate gives the stamps (no --fps)
            assert m.log_time_ns == stamp_ns(DEFAULT_START_NS, FPS, k)
            msg = m.decode()
            assert "jpeg" in msg.format and msg.header.frame_id == cam
            assert bagio.stamp_to_ns(msg.header.stamp) == m.log_time_ns
            img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
            assert img.shape == (H, W, 3)
            # frame k of this camera, through MJPG and JPEG: a few grey levels off at most
            assert np.abs(img.astype(int) - frame_image(c, k)).mean() < 4
        infos = [m.decode() for m in bagio.read_messages(out, [f"/{cam}/camera_info"])]
        assert len(infos) == n
        np.testing.assert_allclose(np.reshape(infos[0].k, (3, 3)), rig[cam].K)
        np.testing.assert_allclose(infos[0].d, rig[cam].D)
    assert "/lobby/image_raw/compressed" not in info.topics
    (videos / "back.yaml").write_text(bagio.read_rig_yaml(out))
    assert Rig.load(videos / "back.yaml").names == rig.names


@pytest.mark.slow
def test_video_bag_cli_with_fps_and_qualisys_rig(tmp_path):
    """The console command users run, on a Qualisys calibration; --fps overrides the videos'."""
    qca = tmp_path / "Calib.qca.txt"
    qca.write_text(
        "<?xml version='1.0'?><calibration><cameras><camera serial='cam01' viewrotation='0'>"
        f"<fov_video left='0' top='0' right='{W - 1}' bottom='{H - 1}'/>"
        "<transform r11='1' r12='0' r13='0' r21='0' r22='1' r23='0' r31='0' r32='0' r33='1' "
        "x='0' y='0' z='3000'/>"
        "<intrinsic focalLengthU='3840' focalLengthV='3840' centerPointU='2048' centerPointV='1536' "
        "radialDistortion1='0' radialDistortion2='0' tangentalDistortion1='0' "
        "tangentalDistortion2='0'/></camera></cameras></calibration>")
    (tmp_path / "videos").mkdir()
    write_video(tmp_path / "videos" / "cam01.avi", 0, frames=3)
    out = tmp_path / "bag"
    done = subprocess.run([sys.executable, "-m", "maem_ros.tools.bags.make_bag", str(out), "--videos",
                           str(tmp_path / "videos"), "--rig", str(qca), "--fps", "60",
                           "--start-stamp", "0", "--quiet"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    stamps = [m.log_time_ns for m in bagio.read_messages(out, ["/cam01/image_raw/compressed"])]
    assert stamps == [0, 16_666_667, 33_333_333]


def test_video_size_must_match_the_calibration(videos, capsys):
    write_video(videos / "videos" / "cam01.avi", 0, size=(W * 2, H * 2))
    code = main([str(videos / "bag"), "--videos", str(videos / "videos"), "--rig",
                 str(videos / "rig.yaml"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert "cam01.avi" in err and "128x96" in err and "calibrated at 64x48" in err
    assert not (videos / "bag").exists()


def test_video_bag_bad_arguments(videos, capsys):
    assert main([str(videos / "b1"), "--videos", str(videos / "nothing"), "--rig",
                 str(videos / "rig.yaml")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (videos / "empty").mkdir()
    assert main([str(videos / "b2"), "--videos", str(videos / "empty"), "--rig",
                 str(videos / "rig.yaml")]) == 2
    assert "named after the rig's cameras" in capsys.readouterr().err
    (videos / "videos" / "cam01.avi").write_bytes(b"not a video")
    assert main([str(videos / "b3"), "--videos", str(videos / "videos"), "--rig",
                 str(videos / "rig.yaml")]) == 2
    assert "cam01.avi" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main([str(videos / "b4"), "--videos", str(videos / "videos")])
    assert e.value.code == 2
    assert "--videos needs --rig" in capsys.readouterr().err
