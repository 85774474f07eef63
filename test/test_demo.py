"""maem-demo: the committed demo bag, its generation, offline and (reduced) graph runs, crashes."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from maem_ros import bagio
from maem_ros.tools.demo import demo, demo_graph

REPO = Path(__file__).resolve().parents[1]
DEMO_BAG = REPO / "bags" / "demo"


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    """The committed demo bag (a small generated one if the checkout has none)."""
    if (DEMO_BAG / "metadata.yaml").is_file():
        return DEMO_BAG
    return demo.make_demo_bag(tmp_path_factory.mktemp("demo") / "bag", frames=14)


def run_cli(args: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    """maem-demo as a subprocess (killed by subprocess.run on timeout). The timeouts are
    generous: a graph of up to 12 processes starts in 10-20 s on a quiet 2-core machine but took
    over 100 s at load 17."""
    return subprocess.run([sys.executable, "-m", "maem_ros.tools.demo.demo", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout_s,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))


# ---- the demo bag ------------------------------------------------------------------------------
def test_committed_bag_contents_and_size():
    if not (DEMO_BAG / "metadata.yaml").is_file():
        pytest.skip("no committed bags/demo in this checkout")
    size = sum(p.stat().st_size for p in DEMO_BAG.iterdir())
    assert size <= 20e6, f"bags/demo is {size / 1e6:.1f} MB"
    d = demo.load_bag(DEMO_BAG)
    assert d.cameras == [f"camera_{i}" for i in range(6)]
    assert len(d.stamps) == demo.DEMO_SCENE["frames"] and sorted(d.gt) == d.stamps
    assert d.scene_config["num_vertices"] == 18439 and d.scene_config["seed"] == 0
    for cam in d.cameras:
        assert d.info.counts[f"/{cam}/image_raw/compressed"] == len(d.stamps)
        assert d.info.counts[f"/{cam}/camera_info"] == len(d.stamps)
        assert d.info.counts[f"/{cam}/detections"] == len(d.stamps)
    demo.check_scene(d)  # the current simulator regenerates this bag's people


@pytest.mark.slow
def test_make_demo_bag_small(tmp_path):
    from maem_ros.ros.wire import msg_to_detections
    out = demo.make_demo_bag(tmp_path / "bag", frames=3)
    d = demo.load_bag(out)
    assert len(d.stamps) == 3 and len(d.gt) == 3
    assert d.scene_config == dict(demo.DEMO_SCENE, frames=3)
    msg = next(bagio.read_messages(out, ["/camera_2/detections"]))
    dets = msg_to_detections(msg.decode(), msg.topic)
    assert dets.n > 0 and dets.num_vertices == demo.BAG_VERTICES
    img = next(bagio.read_messages(out, ["/camera_0/image_raw/compressed"])).decode()
    assert img.format == "jpeg" and bytes(img.data[:2]) == b"\xff\xd8"
    demo.check_scene(d)
    with pytest.raises(ValueError, match="exists already"):
        demo.make_demo_bag(out, frames=3)


@pytest.mark.slow
def test_ensure_bag_generates_only_the_default_and_rejects_non_bags(tmp_path, monkeypatch):
    import maem_ros.tools.demo.demo_bag as demo_bag
    with pytest.raises(bagio.BagError, match="no such file"):  # --bag /typo: nothing created
        demo.ensure_bag(tmp_path / "typo", frames=2)
    assert not (tmp_path / "typo").exists()
    monkeypatch.setattr(demo_bag, "default_bag", lambda: tmp_path / "new")
    bag = demo.ensure_bag(None, frames=2)  # no --bag and no default bag yet: generated
    assert bag == tmp_path / "new" and len(demo.load_bag(bag).stamps) == 2
    assert demo.ensure_bag(bag, frames=5) == bag  # an existing bag is used as it is
    (tmp_path / "junk").mkdir()
    with pytest.raises(bagio.BagError, match="not a rosbag2 folder"):
        demo.ensure_bag(tmp_path / "junk", frames=2)


def test_check_scene_detects_other_simulator(tmp_path, bag):
    d = demo.load_bag(bag)
    d.gt = {s: g + 0.01 for s, g in d.gt.items()}
    with pytest.raises(ValueError, match="another simulator version"):
        demo.check_scene(d)


@pytest.mark.slow
def test_trim_bag_keeps_first_frames_and_metadata(tmp_path, bag):
    d = demo.load_bag(bag)
    out = demo.trim_bag(d, tmp_path / "trim", 4)
    t = demo.load_bag(out)
    assert t.stamps == d.stamps[:4] and sorted(t.gt) == d.stamps[:4]
    assert t.scene_config == d.scene_config and t.rig_yaml == d.rig_yaml
    assert t.info.counts["/camera_3/image_raw/compressed"] == 4
    assert t.info.counts[bagio.SCENE_TOPIC] == 1


# ---- helpers ------------------------------------------------------------------------------------
def test_params_put_frontend_under_wildcard_namespace(tmp_path):
    scene = dict(demo.DEMO_SCENE)
    path = demo_graph.write_params("demo.yaml", tmp_path / "p.yaml", tmp_path / "rig.yaml", scene, 0.7)
    data = yaml.safe_load(path.read_text())
    assert "frontend" not in data and "association" not in data
    fe = data["/**/frontend"]["ros__parameters"]
    assert fe["image_transport"] == "compressed" and json.loads(fe["scene_dict"]) == scene
    assert fe["frames"] == 0 and fe["seed"] == -1 and fe["difficulty"] == ""  # scene_dict rules
    assert data["/**"]["ros__parameters"]["rig"] == str(tmp_path / "rig.yaml")
    assert data["/**/association"]["ros__parameters"]["max_wait"] == 0.7
    assert data["/**/association"]["ros__parameters"]["tau_mesh"] == 8.0
    with pytest.raises(ValueError, match="no scene description"):
        demo_graph.write_params("demo.yaml", tmp_path / "q.yaml", tmp_path / "rig.yaml", None)


def test_node_section_merges_key_forms():
    data = {"association": {"ros__parameters": {"a": 1, "b": 1}},
            "/**/association": {"ros__parameters": {"b": 2}}}
    assert demo_graph.node_section(data, "association") == {"a": 1, "b": 2}
    assert list(data) == ["/**/association"]


def test_stage_timing_merges_frontends():
    diags = {f"/camera_{i}/frontend": {"time_ms/estimate/median": str(10 + i),
                                       "time_ms/estimate/p99": str(20 + i),
                                       "frames_processed": "5", "frames_dropped": "1"}
             for i in range(3)}
    diags["/association"] = {"time_ms/associate/median": "4", "time_ms/associate/p99": "9",
                             "frames_processed": "7", "frames_dropped": "0"}
    rows = demo.stage_timing(diags)
    assert ("association", "associate", 4.0, 9.0, 7, 0) in rows
    assert ("frontend (x3)", "estimate", 11.0, 22.0, 15, 3) in rows


def test_played_frames(bag):
    d = demo.load_bag(bag)
    assert demo.played_frames(d, None, None) == len(d.stamps)
    assert demo.played_frames(d, 5, None) == 5
    assert demo.played_frames(d, 10_000, None) == len(d.stamps)
    assert demo.played_frames(d, None, 0.1) == 4  # frames at 0, 1/30, 2/30, 3/30 s


# ---- runs ---------------------------------------------------------------------------------------
@pytest.mark.slow
def test_offline_demo_accuracy(tmp_path, bag, capsys):
    code = demo.main(["--bag", str(bag), "--out", str(tmp_path), "--no-graph", "--frames", "10"])
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    m = report["metrics"]
    assert m["frames"] == 10
    assert m["recall"] >= 0.8, m
    assert 15 <= m["mpjpe_mean"] <= 60, m
    assert "MPJPE mean" in capsys.readouterr().out
    assert (tmp_path / "court.png").is_file() and (tmp_path / "snapshot_camera_0.png").is_file()


@pytest.mark.timeout(300)
@pytest.mark.ros
@pytest.mark.slow
def test_graph_demo_plays_recorded_detections_in_real_time(tmp_path, bag):
    """The default: the bag's recorded detections at rate 1.0 -> association + triangulation."""
    out = tmp_path / "out"
    r = run_cli(["--bag", str(bag), "--out", str(out), "--frames", "20"], timeout_s=280)
    log = f"stdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    assert r.returncode == 0, log
    report = json.loads((out / "report.json").read_text())
    assert report["frames_played"] == 20 and report["rate"] == 1.0
    assert all(code == 0 for code in report["exit_codes"].values()), log
    assert "frontend" not in " ".join(report["exit_codes"])
    assert report["metrics"]["recall"] >= 0.6, log
    assert report["frames_dropped"] <= 3, log
    assert "/<cam>/detections" in report["latency_definition"]
    assert "played 20/20 frames" in r.stdout, log
    nodes = set(demo.recorded_diagnostics(out / "record"))
    assert {"/association", "/triangulation"} <= nodes and "/camera_0/frontend" not in nodes


@pytest.mark.timeout(300)
@pytest.mark.ros
@pytest.mark.slow
def test_graph_demo_reduced(tmp_path, bag):
    """--frontends: the real node graph (9 processes + player + recorder) on 12 frames."""
    out = tmp_path / "out"
    r = run_cli(["--bag", str(bag), "--out", str(out), "--frames", "12", "--rate", "0.05",
                 "--frontends"], timeout_s=280)
    log = f"stdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    assert r.returncode == 0, log
    report = json.loads((out / "report.json").read_text())
    assert report["frames_played"] == 12
    assert all(code == 0 for code in report["exit_codes"].values()), log
    assert not report["crashed"], log
    m = report["metrics"]
    assert m["recall"] >= 0.6, log
    assert 15 <= m["mpjpe_mean"] <= 70, log
    assert report["frames_dropped"] <= 3, log
    assert report["latency_ms_median"] is not None and report["latency_ms_median"] > 0
    poses = demo.recorded_poses(out / "record")
    assert set(poses) <= set(demo.load_bag(bag).stamps[:12]) and len(poses) >= 9
    nodes = {name for name in demo.recorded_diagnostics(out / "record")}
    assert {"/association", "/triangulation", "/camera_0/frontend"} <= nodes
    for text in ("Recall%", "per-stage timing", "end-to-end latency", "frames dropped"):
        assert text in r.stdout, log
    assert (out / "court.png").is_file() and (out / "snapshot_camera_0.png").is_file()


@pytest.mark.timeout(90)
@pytest.mark.ros
@pytest.mark.slow
def test_graph_demo_reports_node_failure(tmp_path, bag):
    """A node that cannot start (bad parameter) is named with its log, exit code 1, no hang."""
    params = yaml.safe_load((REPO / "config" / "demo.yaml").read_text())
    demo_graph.node_section(params, "association")["tau_mesh"] = -1.0
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(params))
    r = run_cli(["--bag", str(bag), "--out", str(tmp_path / "out"), "--frames", "2",
                 "--params", str(bad), "--startup-timeout", "40"], timeout_s=80)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "association: exit code 2" in r.stderr and "tau_mesh" in r.stderr, r.stderr
