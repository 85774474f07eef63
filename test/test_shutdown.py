"""Stopping a node process: the shutdown watchdog and the SIGUSR1 stack dump (ros/cli.py)."""
from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from maem_ros.ros.cli import SHUTDOWN_STALLED

from helpers_ros import wait_for

pytestmark = pytest.mark.timeout(60)

#: a process whose main loop ignores the stop request (a stalled callback or teardown)
STALLED = textwrap.dedent("""
    import sys, time
    from maem_ros.ros.cli import stop_on_signals
    stop = stop_on_signals("stalled", grace_s=float(sys.argv[1]))
    print("ready", flush=True)
    def stalled_in_callback():
        while True:
            time.sleep(0.01)
    stalled_in_callback()
""")


def start(grace_s: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", STALLED, str(grace_s)], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
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
