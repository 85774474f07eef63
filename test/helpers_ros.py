"""Scaffolding shared by the tests that drive a node (often a subprocess) from a test node:
a node + executor on a private rclpy Context, spinning until a condition, QoS profiles, and
making sure a child process never outlives its test."""
from __future__ import annotations

import subprocess
import time
from contextlib import contextmanager
from typing import Callable, Iterator

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@contextmanager
def ros_node(name: str) -> Iterator[tuple[rclpy.node.Node, SingleThreadedExecutor]]:
    """(node, executor) on a private Context; the test spins the executor itself."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(name, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def wait_for(cond: Callable[[], bool], timeout: float, ex: SingleThreadedExecutor | None = None,
             step: float = 0.02) -> bool:
    """Spin ``ex`` (or sleep, without one) until ``cond()``; its last value after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        if ex is not None:
            ex.spin_once(timeout_sec=step)
        else:
            time.sleep(step)
    return cond()


@contextmanager
def killed_on_exit(proc: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``proc``, killed when the block leaves while it still runs (a failed assertion)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


class OutputWatcher:
    """Collects a child's merged stdout/stderr lines on a thread; ``wait_line(text, timeout)``
    returns once a line containing ``text`` arrived (False at the timeout or the child's end)."""

    def __init__(self, proc: subprocess.Popen):
        import threading
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._done = False
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def wait_line(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not any(text in line for line in self.lines):
                left = deadline - time.monotonic()
                if self._done or left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def text(self) -> str:
        self._thread.join(timeout=5)
        with self._cond:
            return "".join(self.lines)
