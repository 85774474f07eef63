"""Stopping a node process: the shutdown watchdog and the SIGUSR1 stack dump (ros/cli.py), the
Fast DDS teardown guard (ros/fastdds.py)."""
from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from maem_ros.ros.cli import SHUTDOWN_STALLED, STALLED_WITH_GIL

from helpers_ros import ros_node, wait_for

# node shutdown and the Fast DDS teardown guard
pytestmark = [pytest.mark.timeout(60), pytest.mark.ros]

#: a process whose main loop ignores the stop request (a stalled callback or teardown)
STALLED = textwrap.dedent("""
    import sys, time
    from maem_ros.ros.cli import stop_on_signals
    stop = stop_on_signals("stalled", grace_s=float(sys.argv[1]))
    print("ready", flush=True)
    def stalled_in_callback():
        while True:
            time.sleep(0.01)
    def stalled_holding_the_gil():
        while not stop.is_set():
            time.sleep(0.01)
        import re
        re.match(r"(a+)+$", "a" * 64 + "b")  # C code that never lets the GIL go
    stalled_holding_the_gil() if sys.argv[2:] == ["gil"] else stalled_in_callback()
""")


#: every process start() made, killed when the test ends: a stalled one that outlives a failed
#: test would spin on a core (the GIL-holding stall never ends by itself)
_STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def _kill_started():
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def start(grace_s: float, *how: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", STALLED, str(grace_s), *how], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _STARTED.append(proc)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_watchdog_ends_a_stalled_process_after_the_grace_with_its_stacks():
    proc = start(grace_s=1.0)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert time.monotonic() - t0 >= 1.0
    assert f"[stalled] {SHUTDOWN_STALLED} 1 s after the stop signal" in err
    assert "stalled_in_callback" in err  # where it was stuck


def test_watchdog_backstop_ends_a_process_stalled_holding_the_gil():
    """A teardown stalled in C code that holds the GIL (rclpy's destroy_node seen so) keeps the
    watchdog thread from waking: faulthandler's thread dumps the stacks and exits 1, 1 s later."""
    proc = start(1.0, "gil")
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 1, err
    assert time.monotonic() - t0 >= 2.0
    assert err.startswith(STALLED_WITH_GIL) and "stalled_holding_the_gil" in err, err
    assert SHUTDOWN_STALLED not in err


def test_sigusr1_dumps_stacks_and_the_process_keeps_running():
    proc = start(grace_s=30.0)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        proc.send_signal(signal.SIGUSR1)
        assert wait_for(lambda: any("stalled_in_callback" in ln for ln in lines), 20.0), lines
        assert proc.poll() is None
    finally:
        proc.kill()
        proc.wait(timeout=10)
    reader.join(timeout=10)
    assert not any(SHUTDOWN_STALLED in ln for ln in lines)


def test_without_a_signal_the_watchdog_never_fires():
    proc = start(grace_s=0.1)
    try:
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=1.0)
    finally:
        proc.kill()
        proc.communicate(timeout=10)


def test_detached_discovery_listener_stops_its_own_participants_discovery_only():
    """ros/fastdds.py: once a node's participant has its discovery listener detached, no
    discovery callback runs there (so the detach rmw makes at destroy_node, whose wait cannot
    end while one runs, returns at once): it learns of no new endpoint, while another
    participant of the same process does; and the node is then destroyed as usual."""
    import rclpy
    from std_msgs.msg import String

    from maem_ros.ros.fastdds import detach_discovery_listener

    with ros_node("guard_detached") as (detached, _), ros_node("guard_watching") as (watching, _):
        if rclpy.get_rmw_implementation_identifier() != "rmw_fastrtps_cpp":
            pytest.skip("the guard is for rmw_fastrtps_cpp")
        assert detach_discovery_listener(detached)
        with ros_node("guard_late") as (late, _):
            late.create_publisher(String, "/guard_late", 10)
            assert wait_for(lambda: watching.count_publishers("/guard_late") == 1, 20.0)
            # the watching participant has discovered it: the detached one had the same chance
            assert not wait_for(lambda: detached.count_publishers("/guard_late") > 0, 2.0)
