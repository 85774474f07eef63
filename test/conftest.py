"""Test-session isolation: a private ROS_DOMAIN_ID and localhost-only discovery.

Set before any test imports rclpy so every node (in-process or subprocess, which
inherits the environment) of this session lives in its own DDS domain.
MAEM_TEST_DOMAIN_ID picks the domain instead of chance, for concurrent sessions on one
machine that must not hear each other.
"""
import os
import random

os.environ["ROS_DOMAIN_ID"] = os.environ.get("MAEM_TEST_DOMAIN_ID") or str(
    random.SystemRandom().randint(1, 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402 - after the environment above

from helpers_ros import SCENE, Graph  # noqa: E402


#: markers a test gets from the fixtures it uses (markers: setup.cfg [tool:pytest]; make test-fast
#: deselects ros, slow, colcon and network); tests that start nodes otherwise are marked in their file
FIXTURE_MARKERS = {
    "graph": ("ros",),  # an in-process node graph on a DDS participant
    "pose2sim_demo": ("network", "slow"),  # downloads the pose2sim wheel once per cache
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        for fixture in item.fixturenames:
            for name in FIXTURE_MARKERS.get(fixture, ()):
                item.add_marker(name)


@pytest.fixture
def graph():
    """An in-process node graph on a private Context (helpers_ros.Graph), closed after the test."""
    g = Graph()
    yield g
    g.close()


@pytest.fixture(scope="module")
def scene():
    """The graph tests' synthetic scene (helpers_ros.SCENE), epipolar kernel compiled."""
    import maem_ros.sim.scene as sim
    from maem_ros.core.association.pipeline import AssociationParams, associate
    sc = sim.Scene(sim.SceneConfig(**SCENE))
    # compile the epipolar kernel (numba) before any node runs: a first-frame stall longer than
    # max_wait would make the synchroniser treat every camera as dead for one frame
    associate(sc.rig, {c: sc.detections(c, 0) for c in sc.rig.names}, AssociationParams())
    from maem_ros.core.triangulation import ransac_kernel as triangulation_kernel
    triangulation_kernel.warmup()  # the triangulation node's RANSAC kernel likewise
    return sc


@pytest.fixture(scope="session")
def pose2sim_demo():
    """Pose2Sim's Demo_MultiPerson folder (real calibration + videos) from the pose2sim wheel,
    downloaded into the maem_ros cache once; the test skips when the wheel cannot be had."""
    from maem_ros.tools.demo.pose2sim_demo import POSE2SIM_VERSION, fetch_demo
    try:
        return fetch_demo(timeout_s=300.0)
    except RuntimeError as e:
        pytest.skip(f"pose2sim=={POSE2SIM_VERSION} wheel (the real footage) not available: {e}")


@pytest.fixture(scope="session")
def mediapipe_installed():
    """Skips unless the optional mediapipe wheel is installed (make mediapipe)."""
    from maem_ros.frontend.mediapipe_pose import import_mediapipe
    try:
        return import_mediapipe()
    except ImportError as e:
        pytest.skip(str(e))
