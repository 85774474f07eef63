"""core.synthetic: the simulated frame sets of the bench's load and of the nodes' warm passes."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from maem_ros.core.geometry.camera import Rig
from maem_ros.core.synthetic import rig_focus, warm_sequence
from maem_ros.sim.rigs import load_rig
from maem_ros.tools.bench.bench_load import ring_rig


def test_rig_focus_is_the_point_every_camera_looks_at() -> None:
    """ring_rig aims every camera at (0, 0, 0.8) m: the point nearest to all optical axes."""
    np.testing.assert_allclose(rig_focus(ring_rig(8)), [0.0, 0.0, 0.8], atol=1e-9)


@pytest.mark.parametrize("rig_name", ["sportcenter6", "lab4", "humanm3_3", "humanm3_4"])
def test_warm_sequence_shows_people_to_every_camera_of_the_shipped_rigs(rig_name: str) -> None:
    """Every shipped rig gets frame sets (two frames: the second runs a track stage's
    track-assisted path) in which every camera sees the same people, inside its image."""
    rig = load_rig(rig_name)
    sequence = warm_sequence(rig)
    assert len(sequence) == 2
    for frame_set in sequence:
        counts = {cam: fd.n for cam, fd in frame_set.frames.items()}
        assert set(counts) == set(rig.names)
        assert len(set(counts.values())) == 1 and min(counts.values()) >= 1, counts
        assert all(len(cluster) == len(rig) for cluster in frame_set.truth)
        for cam in rig.cameras:
            bboxes = frame_set.frames[cam.name].bboxes
            assert np.all(bboxes[:, :2] > -cam.width) and np.all(bboxes[:, 2:] < 2 * cam.width)


def test_warm_sequence_says_when_the_cameras_share_no_view() -> None:
    """Cameras that look away from each other share no floor: a ValueError, not a hang."""
    turn = np.diag([-1.0, 1.0, -1.0])  # half a turn about each camera's own y axis, centre kept
    rig = Rig([replace(c, R=turn @ c.R, t=turn @ c.t) for c in ring_rig(4).cameras])
    with pytest.raises(ValueError, match="cannot place a person"):
        warm_sequence(rig)
