"""The real-footage path end to end, as a user runs it: Pose2Sim's videos + Qualisys calibration ->
maem-make-bag --videos -> maem-demo --backend mediapipe (the real node graph) -> report.json.

Needs the pose2sim wheel (fetched into the cache) and the mediapipe wheel (make mediapipe);
skips with the reason otherwise.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maem_ros import bagio
from maem_ros.tools.bags.make_bag import main as make_bag_main

# the mediapipe graph on the pose2sim footage (network: the fixture)
pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]


def test_mediapipe_graph_on_real_frames(tmp_path, pose2sim_demo, mediapipe_installed):
    bag = tmp_path / "bag"
    assert make_bag_main([str(bag), "--videos", str(pose2sim_demo / "videos"), "--rig",
                          str(pose2sim_demo / "calibration" / "Calib.qca.txt"), "--quiet",
                          "--jpeg-quality", "80"]) == 0
    info = bagio.bag_info(bag)
    assert {f"/cam0{k}/image_raw/compressed" for k in range(1, 5)} <= set(info.topics)
    out = tmp_path / "out"
    # the default replay: lockstep on /maem/clusters, images reliable, so however slow the four
    # CPU frontends are on this machine, each of them gets every image of the 3 frames
    done = subprocess.run([sys.executable, "-m", "maem_ros.tools.demo.demo", "--bag", str(bag),
                           "--backend", "mediapipe", "--out", str(out), "--frames", "3"],
                          cwd=REPO, capture_output=True, text=True,
                          timeout=280, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["backend"] == "mediapipe"
    assert len(report["people_per_frame"]) == 3
    assert min(report["people_per_frame"]) >= 2, report["people_per_frame"]
    assert report["reprojection_px_mean_inliers"] < 10.0
    assert report["reprojection_px_mean"] <= report["reprojection_px_mean_all_members"]
    assert 0 <= report["reprojection_members_rejected"] < report["reprojection_members"]
    assert "reprojection_px_mean averages" in report["reprojection_definition"]
    for cam in ("cam01", "cam02", "cam03", "cam04"):
        assert (out / f"snapshot_{cam}.png").is_file()
    assert "no accuracy table" in done.stdout
    frontend = [r for r in report["timing"] if r["node"].startswith("frontend")
                and r["stage"] == "estimate"]
    assert frontend and frontend[0]["processed"] == 4 * 3  # no image lost on the way
