"""Command-line plumbing shared by the bag nodes (maem-play, maem-record), which parse their own
arguments and handle SIGINT/SIGTERM themselves. No rclpy import here (``--help`` stays fast)."""
from __future__ import annotations

import signal
import threading
from typing import Sequence


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(our arguments, rclpy arguments): everything from the first ``--ros-args`` on is rclpy's.

    rclpy's ``remove_ros_args`` is not used because it also swallows ``a:=b`` (legacy remap
    syntax), which is maem-play's ``--remap`` value format.
    """
    argv = list(argv)
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    return argv[1:cut], argv[:1] + argv[cut:]


def stop_on_signals() -> threading.Event:
    """An Event set by SIGINT or SIGTERM (the caller then finishes cleanly: rclpy is initialised
    with ``SignalHandlerOptions.NO``)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop
