"""ROS conventions a user relies on: ``--help`` on every node, relative output topics that
follow ``-r __ns:=``, ``-p node:param:=value`` after a params file."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from sensor_msgs.msg import PointCloud2

from maem_ros.ros import wire
from maem_ros.ros.probe import fusion_links
from maem_ros.ros.qos import DATA_QOS

from helpers_ros import (
    DiagnosticsReader,
    OutputWatcher,
    killed_on_exit,
    ros_node,
    wait_for,
    wait_links_matched,
)

# node command lines (--help too), namespaces, parameters, diagnostics
pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
PARAM_NODES = {"frontend": "maem_ros.ros.frontend_node",
               "association": "maem_ros.ros.association_node",
               "triangulation": "maem_ros.ros.triangulation_node",
               "camera": "maem_ros.ros.camera_node",
               "foxglove": "maem_ros.ros.foxglove_node"}


@pytest.mark.parametrize("node", sorted(PARAM_NODES))
def test_help_lists_every_parameter_and_exits_0(node: str) -> None:
    import importlib
    module = importlib.import_module(PARAM_NODES[node])
    out = subprocess.run([str(BIN / node), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: ros2 run maem_ros {node} ")
    lines = {line.strip().split(" ", 1)[0]: line for line in out.stdout.splitlines()
             if line.startswith("  ")}
    specs = list(module.PARAMS) + ([module.SOURCE] if node == "camera" else [])
    for spec in specs:
        assert spec.name in lines, f"{spec.name} missing from {node} --help"
        assert f"default {spec.default!r}" in lines[spec.name] and spec.description in \
            lines[spec.name]


@pytest.mark.parametrize("node", ["player", "recorder"])
def test_help_of_the_bag_nodes(node: str) -> None:
    out = subprocess.run([str(BIN / node), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("usage:"), out.stderr


def _start(cmd: list[str]) -> tuple[subprocess.Popen, OutputWatcher]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, OutputWatcher(proc)


def test_namespaced_graph_publishes_under_the_namespace(tmp_path: Path) -> None:
    """association + triangulation started with -r __ns:=/team read /team/<cam>/detections and
    deliver /team/maem/poses; a second params file overrides the first (what works for a
    namespaced node: rcl's ``-p node:name:=value`` only matches a node in /)."""
    import maem_ros.sim.scene as sim
    scene = sim.Scene(sim.SceneConfig(rig="sportcenter6", frames=4, seed=3, difficulty="easy",
                                      num_vertices=500))
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({
        "/**": {"ros__parameters": {"rig": "sportcenter6", "diagnostics_period": 0.5}},
        "/**/association": {"ros__parameters": {"tau_det": 0.5, "max_wait": 1.0,
                                                "confirm_hits": 1}},  # ids from frame 0 on
        "/**/triangulation": {"ros__parameters": {"track_min_hits": 1, "publish_tentative": False}},
    }))
    override = tmp_path / "override.yaml"
    override.write_text(yaml.safe_dump({"/**/triangulation": {"ros__parameters": {
        "tau_kps": 25.0}}}))
    base = ["--ros-args", "--params-file", str(params), "-r", "__ns:=/team"]
    assoc, assoc_out = _start([str(BIN / "association"), *base])
    tri, tri_out = _start([str(BIN / "triangulation"), *base, "--params-file", str(override)])
    with killed_on_exit(assoc), killed_on_exit(tri), ros_node("ns_client") as (node, ex):
        assert assoc_out.wait_line("-> /team/maem/clusters", 120), assoc_out.text()
        assert tri_out.wait_line("/team/maem/clusters -> /team/maem/poses", 120), tri_out.text()
        got: dict[int, wire.PoseFrame] = {}
        node.create_subscription(PointCloud2, "/team/maem/poses", lambda m: got.setdefault(
            wire.stamp_to_ns(m.header.stamp), wire.msg_to_poses(m, "/team/maem/poses")), DATA_QOS)
        pubs = {c: node.create_publisher(PointCloud2, f"/team/{c}/detections", DATA_QOS)
                for c in scene.rig.names}
        assert wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 60, ex)
        # and matched at the nodes' ends (their /diagnostics): the first frame is sent once
        diags = DiagnosticsReader(node)
        wait_links_matched(diags, fusion_links(scene.rig.names, image_topic=None,
                                               namespace="/team"), 60, ex)
        for f in range(scene.num_frames):
            for cam, pub in pubs.items():
                pub.publish(wire.detections_to_msg(scene.detections(cam, f)))
            if f == 0:  # first use (kernel compile or cache load, discovery of the poses
                # topic) can take seconds on a fresh clone: the frame rate starts after it
                assert wait_for(lambda: scene.stamp_ns(0) in got, 120, ex), \
                    f"no poses for frame 0\n{assoc_out.text()}\n{tri_out.text()}"
            t_end = time.monotonic() + 0.2
            wait_for(lambda: time.monotonic() > t_end, 1.0, ex)
        stamps = [scene.stamp_ns(f) for f in range(scene.num_frames)]
        assert wait_for(lambda: all(s in got for s in stamps), 60, ex), \
            f"{len(got)}/{len(stamps)} frames\n{assoc_out.text()}\n{tri_out.text()}"
        assert all(len(got[s].ids) >= scene.is_player.sum() // 2 for s in stamps), \
            [len(got[s].ids) for s in stamps]
        # the second params file's value reached the node
        desc = subprocess.run([sys.executable, "-c", _GET_PARAM, "/team/triangulation", "tau_kps"],
                              capture_output=True, text=True, timeout=60)
        assert desc.stdout.strip() == "25.0", desc.stdout + desc.stderr
        for proc in (assoc, tri):
            proc.send_signal(signal.SIGINT)
        assert assoc.wait(30) == 0 and tri.wait(30) == 0


#: `ros2 param get` without ros2cli: the GetParameters service of a running node
_GET_PARAM = """
import sys, rclpy
from rcl_interfaces.srv import GetParameters
rclpy.init()
node = rclpy.create_node("param_get")
cli = node.create_client(GetParameters, sys.argv[1] + "/get_parameters")
assert cli.wait_for_service(timeout_sec=30)
fut = cli.call_async(GetParameters.Request(names=[sys.argv[2]]))
rclpy.spin_until_future_complete(node, fut, timeout_sec=30)
print(fut.result().values[0].double_value)
"""


@pytest.mark.parametrize("override,expected", [
    (["-p", "triangulation:tau_kps:=25.0"], 25.0),  # node-specific -p after the file: wins
    (["-p", "tau_kps:=25.0"], 20.0),  # a wildcard -p loses to the file's /**/triangulation
])
def test_p_node_param_after_the_shipped_params_file(override: list[str], expected: float) -> None:
    """What README says about -p next to --params-file, with the installed share path."""
    import rclpy

    from maem_ros.params import resolve_config_path
    from maem_ros.ros.triangulation_node import TriangulationNode

    shipped = resolve_config_path("sportcenter.yaml")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=["triangulation", "--ros-args", "--params-file", str(shipped),
                                  *override])
    try:
        node = TriangulationNode(context=ctx)
        assert node.params.tau_kps == expected
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_diagnostics_keep_coming_with_use_sim_time_and_no_clock() -> None:
    """The diagnostics timer runs on the steady clock: with use_sim_time and nobody publishing
    /clock (sim time stands still at 0) /diagnostics still arrives every period."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.parameter import Parameter

    from maem_ros.ros.qos import DIAGNOSTICS_QOS
    from maem_ros.ros.triangulation_node import TriangulationNode

    with ros_node("diag_listener") as (client, ex):
        got = []
        client.create_subscription(DiagnosticArray, "/diagnostics", lambda m: got.extend(
            s for s in m.status if s.name == "/triangulation"), DIAGNOSTICS_QOS)
        node = TriangulationNode(context=client.context, parameter_overrides=[
            Parameter("rig", value="sportcenter6"), Parameter("diagnostics_period", value=0.2),
            Parameter("use_sim_time", value=True)])
        ex.add_node(node)
        try:
            assert node.get_clock().now().nanoseconds == 0  # sim time, no /clock
            assert wait_for(lambda: len(got) >= 3, 20, ex), len(got)
        finally:
            ex.remove_node(node)
            node.destroy_node()


def test_diagnostics_report_matched_endpoints_per_topic() -> None:
    """/diagnostics says, per data topic, how many endpoints DDS matched at this node's end:
    0 on /maem/clusters until a subscriber appears, then 1; a client waits on these (not on the
    ROS graph listing) before it sends, so nothing it sends before matching is lost."""
    from rclpy.parameter import Parameter

    from maem_ros.ros.probe import unmatched_links
    from maem_ros.ros.triangulation_node import TriangulationNode

    with ros_node("diag_listener") as (client, ex):
        diags = DiagnosticsReader(client)
        node = TriangulationNode(context=client.context, parameter_overrides=[
            Parameter("rig", value="sportcenter6"), Parameter("diagnostics_period", value=0.2)])
        ex.add_node(node)
        try:
            tri = ("/triangulation", "matched_publishers/maem/clusters")
            assert wait_for(lambda: diags.get(tri[0]), 20, ex)
            assert diags.get(tri[0])[tri[1]] == "0"
            assert unmatched_links(diags.snapshot(), [tri]) == [f"{tri[0]}:{tri[1]}"]
            assert not any(k.endswith(("/rosout", "/diagnostics")) for k in diags.get(tri[0]))
            client.create_publisher(PointCloud2, "/maem/clusters", DATA_QOS)
            assert wait_for(lambda: diags.get(tri[0]).get(tri[1]) == "1", 20, ex), \
                diags.get(tri[0])
            assert unmatched_links(diags.snapshot(), [tri]) == []
            links = fusion_links(["camera_0"], image_topic=None)
            assert tri in links
            assert ("/association", "matched_publishers/camera_0/detections") in links
            assert all(not k.endswith("image_raw") for _, k in links)
        finally:
            ex.remove_node(node)
            node.destroy_node()


def test_fusion_links_between_the_graphs_own_nodes() -> None:
    """sources=False: the links a tool can check before its player starts (maem-demo); a count
    can be required above one (two readers of /maem/poses: recorder and listener)."""
    from maem_ros.ros.probe import unmatched_links

    full = fusion_links(["a", "b"], image_topic="image_raw")
    own = fusion_links(["a", "b"], image_topic="image_raw", sources=False)
    assert [link for link in full if link not in own] == [
        ("/a/frontend", "matched_publishers/a/image_raw"),
        ("/b/frontend", "matched_publishers/b/image_raw")]
    assert ("/association", "matched_publishers/a/detections") in own  # frontend -> association
    without_frontends = fusion_links(["a", "b"], image_topic=None, sources=False)
    assert without_frontends == [("/association", "matched_subscribers/maem/clusters"),
                                 ("/triangulation", "matched_publishers/maem/clusters"),
                                 ("/triangulation", "matched_subscribers/maem/poses")]
    diags = {"/association": {"matched_subscribers/maem/clusters": "1"},
             "/triangulation": {"matched_publishers/maem/clusters": "1",
                                "matched_subscribers/maem/poses": "1"}}
    assert unmatched_links(diags, without_frontends) == []
    assert unmatched_links(diags, without_frontends,
                           at_least={"matched_subscribers/maem/poses": 2}) == [
        "/triangulation:matched_subscribers/maem/poses"]
