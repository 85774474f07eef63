"""Command-line plumbing: ``--help`` of the nodes, signals and rclpy init/shutdown, shared by
run_node and the bag nodes (maem-play, maem-record), which parse their own arguments. No rclpy
import here (``--help`` stays fast)."""

from __future__ import annotations

import faulthandler
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.node import Node

    from maem_ros.core.paramspec import ParamSpec

#: exit code of a command whose input (arguments, params file, bag) is invalid
EXIT_BAD_INPUT = 2


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(our arguments, rclpy arguments): everything from the first ``--ros-args`` on is rclpy's.

    rclpy's ``remove_ros_args`` is not used because it also swallows ``a:=b`` (legacy remap
    syntax), which is maem-play's ``--remap`` value format.
    """
    argv = list(argv)
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    return argv[1:cut], argv[:1] + argv[cut:]


#: s a node may take from SIGINT/SIGTERM to exit before its watchdog ends the process
SHUTDOWN_GRACE_S = 10.0
#: what the watchdog's line says (tools/processes.py looks for it in the logs)
SHUTDOWN_STALLED = "shutdown did not finish"


def stop_on_signals(name: str = "", grace_s: float | None = SHUTDOWN_GRACE_S) -> threading.Event:
    """An Event set by SIGINT or SIGTERM (the caller then finishes cleanly: rclpy is initialised
    with ``SignalHandlerOptions.NO``).

    SIGUSR1 dumps every thread's Python stack to stderr (faulthandler), so a process that does
    not stop can be asked where it is. With ``grace_s``, a watchdog thread ends the process
    ``grace_s`` seconds after the signal if it is still running (a callback or the middleware's
    teardown stalled): it prints one line and the stacks, then exits with code 0, as a stop was
    requested and every processed message has been published by then. If the stall holds the
    GIL (C code; the thread cannot wake), faulthandler's own thread dumps the stacks and exits
    with code 1 a second later (its dump begins with STALLED_WITH_GIL). The recorder passes
    None: its bag must be finalised whatever it takes. The event is also set by the caller
    when it begins its teardown by itself.
    """
    stop = threading.Event()
    armed = threading.Event()  # the GIL-free backstop is set (_arm_backstop)

    def on_signal(*_: object) -> None:
        # the backstop is armed here, in the main thread, before the interrupted code resumes:
        # armed by the watchdog thread alone, a main thread that went straight from the stop
        # into C code holding the GIL would keep that thread from ever arming it
        if grace_s is not None:
            _arm_backstop(armed, grace_s)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    if grace_s is not None:
        threading.Thread(
            target=_exit_after_grace, args=(stop, armed, name, grace_s), daemon=True, name="shutdown-watchdog"
        ).start()
    return stop


#: how faulthandler's timed dump begins (the watchdog's backstop, see _arm_backstop)
STALLED_WITH_GIL = "Timeout ("


def _arm_backstop(armed: threading.Event, grace_s: float) -> None:
    """Backstop without the GIL, once: a teardown stalled inside C code that holds it (seen:
    rclpy's destroy_node -> destroy_when_not_in_use, 1 run in ~35 of maem-bench --live, until
    ros/fastdds.py removed that deadlock's cause) keeps the watchdog thread from waking;
    faulthandler's own thread then dumps the stacks and exits 1, grace_s + 1 s after the stop."""
    if not armed.is_set():
        armed.set()
        faulthandler.dump_traceback_later(grace_s + 1.0, exit=True)


def _exit_after_grace(stop: threading.Event, armed: threading.Event, name: str, grace_s: float) -> None:
    stop.wait()
    _arm_backstop(armed, grace_s)  # a stop set by the caller, not by a signal
    time.sleep(grace_s)
    print(
        f"[{name}] {SHUTDOWN_STALLED} {grace_s:g} s after the stop signal; exiting "
        f"without it (stacks follow)",
        file=sys.stderr,
        flush=True,
    )
    faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
    sys.stderr.flush()
    os._exit(0)


def rcl_error_line(e: Exception) -> str:
    """rcl's error text on one line, without its C source locations (``, at /x/y.c:12``)."""
    text = " ".join(str(e).split())
    return re.sub(r",? at [^,]*\.c:\d+", "", text).strip()


def params_file_problem(args: Sequence[str] | None) -> str | None:
    """The first ``--params-file`` after ``--ros-args`` that is missing or not YAML, as one
    line (rcl would log its own error line and a C traceback for it), else None."""
    import yaml

    args = list(args or [])
    if "--ros-args" not in args:
        return None
    ros = args[args.index("--ros-args") + 1 :]
    for flag, path in zip(ros, ros[1:] + [None]):
        if flag != "--params-file":
            continue
        if path is None:
            return "--params-file: missing file name"
        try:
            with open(path, encoding="utf-8") as f:
                data = yaml.safe_load(f)
        except OSError as e:
            return f"--params-file {path!r}: {e.strerror or e}"
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            where = f" (line {mark.line + 1})" if mark is not None else ""
            return f"--params-file {path!r}: not valid YAML{where}: {getattr(e, 'problem', None) or e}"
        if not isinstance(data, dict):
            return f"--params-file {path!r}: expected a mapping of node names, got {type(data).__name__}"
    return None


def init_ros(args: Sequence[str] | None, name: str) -> bool:
    """rclpy.init without rclpy's signal handler; on bad ``--ros-args`` (unknown argument,
    missing or unparsable --params-file) print one line naming them and return False."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    problem = params_file_problem(sys.argv if args is None else args)
    if problem is not None:
        print(f"[{name}] invalid configuration: {problem}", file=sys.stderr, flush=True)
        return False
    try:
        rclpy.init(args=None if args is None else list(args), signal_handler_options=SignalHandlerOptions.NO)
    except Exception as e:  # noqa: BLE001 - RCLError / UnknownROSArgsError from the C layer
        what = "unknown ROS arguments" if type(e).__name__ == "UnknownROSArgsError" else "ROS arguments"
        print(f"[{name}] invalid configuration: {what}: {rcl_error_line(e)}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return False
    return True


def shutdown_ros(node: Node | None, context: Context | None = None) -> None:
    """The end of a command's ROS session: destroy ``node`` (the last node of its context;
    None: none was made) and shut rclpy (``context``, default the global one) down. The node's
    DDS discovery listener is detached first (ros/fastdds.py: a teardown deadlock of the PyPI
    Fast DDS build, hit when the processes of a graph stop together)."""
    import rclpy

    from maem_ros.ros.fastdds import detach_discovery_listener

    if node is not None:
        detach_discovery_listener(node)
        node.destroy_node()
    rclpy.try_shutdown(context=context)


def print_help(name: str, doc: str | None, specs: Sequence[ParamSpec]) -> None:
    """``--help`` of a node: usage, the module docstring's first paragraph, every parameter
    with type, default, constraints and description."""
    summary = (doc or "").strip().split("\n\n", 1)[0].strip()
    lines = [
        f"usage: ros2 run maem_ros {name} [--ros-args [--params-file FILE] "
        f"[-p {name}:NAME:=VALUE] [-r __ns:=/NS] ...]",
        "",
        summary,
        "",
        "parameters (read-only, set at start):",
    ]
    lines += [f"  {spec.help_line()}" for spec in specs]
    print("\n".join(lines), flush=True)


def wants_help(args: Sequence[str] | None) -> bool:
    """``-h``/``--help`` before any ``--ros-args``."""
    argv = list(sys.argv if args is None else args)[1:]
    if "--ros-args" in argv:
        argv = argv[: argv.index("--ros-args")]
    return "-h" in argv or "--help" in argv
