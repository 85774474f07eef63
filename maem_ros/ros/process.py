"""A node process: the DDS profile, the executor, heap tuning (glibc malloc), gc.freeze and
run_node, the main() of every processing node."""

from __future__ import annotations

import gc
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

from maem_ros.core.paramspec import ParamSpec
from maem_ros.ros.cli import init_ros, print_help, shutdown_ros, stop_on_signals, wants_help
from maem_ros.ros.params import EXIT_CONFIG_ERROR, ConfigError

#: environment variables Fast DDS reads its XML profiles file from (either one)
DDS_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_shipped_dds_profile() -> str | None:
    """Point Fast DDS at the shipped config/fastdds.xml (shared memory with a 256 MiB segment
    plus UDPv4, see the file) unless the user chose a profile or another RMW. Call before
    rclpy.init; child processes inherit it. Returns the file now in use (None = untouched)."""
    import os

    if any(os.environ.get(v) for v in DDS_PROFILE_VARS):
        return None
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    from maem_ros.params import config_dirs

    for d in config_dirs():
        if (d / "fastdds.xml").is_file():
            os.environ[DDS_PROFILE_VARS[0]] = str(d / "fastdds.xml")
            return os.environ[DDS_PROFILE_VARS[0]]
    return None


#: environment variable choosing the executor of run_node (EXECUTORS; default "single")
EXECUTOR_VAR = "MAEM_EXECUTOR"
EXECUTORS = ("single", "events")


def make_executor(context=None):
    """The executor a node process spins on ``context`` (rclpy's default when None), chosen
    by ``MAEM_EXECUTOR``: ``single`` (default), rclpy's SingleThreadedExecutor (which takes
    the samples of subscriptions made with ``into_array`` into arrays, ros.raw_take), or ``events``,
    rclpy's experimental EventsExecutor (Jazzy 7.1), which dispatches from rmw callbacks in C++
    instead of rebuilding a wait set in Python on every wake-up (a cost that grows with the
    node's subscriptions, timers and parameter services, and shows most on an idle node woken
    by a fast timer). Both run the callbacks in this thread, one at a time. Not the default:
    with the association node's poll timer armed only while a frame set waits, the two cost
    the same within measurement noise in a closed loop, and the EventsExecutor is marked
    experimental upstream."""
    import os

    choice = os.environ.get(EXECUTOR_VAR, "single") or "single"
    if choice not in EXECUTORS:
        raise ConfigError(f"environment {EXECUTOR_VAR}={choice!r}: expected one of {list(EXECUTORS)}")
    if choice == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    from maem_ros.ros.raw_take import ArrayTakeExecutor

    return ArrayTakeExecutor(context=context)


def spin_slices(
    executor, stop: Callable[[], bool], until: Future | None = None, slice_s: float = 0.1
) -> None:
    """Spin ``executor`` in slices of ``slice_s`` until ``stop()`` (checked between slices) or
    rclpy shuts down; ``until``: a future that also ends a slice when it completes."""
    pending = until if until is not None else Future()
    while not stop() and rclpy.ok():
        if isinstance(executor, SingleThreadedExecutor):
            executor.spin_once(timeout_sec=slice_s)
        else:
            executor.spin_until_future_complete(pending, timeout_sec=slice_s)


#: glibc mallopt parameters (malloc.h) and the values keep_freed_memory sets
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's maximum on 64-bit
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024
#: environment variable overriding a node's heap prefault (MiB, 0 = none)
HEAP_PREFAULT_VAR = "MAEM_HEAP_PREFAULT_MB"
_PREFAULT_CHUNK = 4 * 1024 * 1024  # below the mmap threshold: served from (and freed to) the heap


def keep_freed_memory(prefault_mb: int = 0) -> bool:
    """Let glibc keep freed memory for reuse instead of returning it to the kernel (mallopt:
    mmap threshold 32 MiB, trim threshold 1 GiB), then grow the heap by ``prefault_mb`` MiB,
    touched once and freed (``MAEM_HEAP_PREFAULT_MB`` overrides it); True if set (False off
    glibc, where the allocator has its own policy).

    Why: every received 1.8 MB full-mesh message is one rmw buffer and one Python bytes object
    (and decoded arrays), each above glibc's default mmap / trim thresholds, so each was mapped
    fresh and page-faulted in: hundreds of faults per message taken and thousands in the first
    association step, which made the first frame sets of a live stream late (the node, near
    its CPU budget at 30 fps, then took seconds to catch up; page faults are expensive in
    virtual machines). With the heap kept and prefaulted, the receive path
    takes no page fault from the first message on. Memory stays at the process's peak use."""
    import ctypes
    import ctypes.util
    import os

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    try:
        mb = int(os.environ.get(HEAP_PREFAULT_VAR, prefault_mb))
    except ValueError:
        value = os.environ[HEAP_PREFAULT_VAR]
        raise ConfigError(f"environment {HEAP_PREFAULT_VAR}={value!r}: expected MiB as an integer") from None
    if ok and mb > 0:
        _prefault_heap(libc, mb * 1024 * 1024)
    return ok


def _prefault_heap(libc, nbytes: int) -> None:
    """malloc ``nbytes`` in chunks below the mmap threshold, touch every page, free them: the
    heap keeps the touched pages (trim threshold above ``nbytes``) for later allocations."""
    import ctypes

    malloc, free, memset = libc.malloc, libc.free, libc.memset
    malloc.restype = ctypes.c_void_p
    free.argtypes = [ctypes.c_void_p]
    memset.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t]
    chunks = [malloc(_PREFAULT_CHUNK) for _ in range(max(nbytes // _PREFAULT_CHUNK, 1))]
    for c in chunks:
        if c:
            memset(c, 0, _PREFAULT_CHUNK)
    for c in reversed(chunks):  # top first: the freed chunks coalesce into one free top
        if c:
            free(c)


def run_node(
    make_node: Callable[[], Node],
    args: list[str] | None,
    name: str,
    until: Callable[[Node], Future] | None = None,
    specs: Sequence[ParamSpec] = (),
    doc: str | None = None,
    heap_prefault_mb: int = 0,
) -> int:
    """rclpy.init, build the node, spin until SIGINT/SIGTERM, or with ``until`` until the future
    it returns for the node completes (its result is the exit code). Exit code 0 at
    SIGINT/SIGTERM, EXIT_CONFIG_ERROR (2) on bad params; the node is destroyed either way.

    rclpy's own signal handler is not installed: the executor spins in short slices and a
    Python handler sets an Event, so shutdown always runs from the main thread between
    callbacks (with rclpy's C-level handler we saw rare hangs and SIGSEGV at Ctrl-C).
    ``-h``/``--help`` prints ``doc``'s summary and ``specs`` (print_help) and returns 0.
    ``heap_prefault_mb``: heap grown and touched before the node starts (keep_freed_memory).
    """
    if wants_help(args):
        print_help(name, doc, specs)
        return 0
    stop = stop_on_signals(name)
    use_shipped_dds_profile()
    try:
        keep_freed_memory(heap_prefault_mb)
    except ConfigError as e:
        print(f"[{name}] invalid configuration: {e}", file=sys.stderr, flush=True)
        return EXIT_CONFIG_ERROR
    if not init_ros(args, name):
        return EXIT_CONFIG_ERROR
    node = None
    try:
        try:
            node = make_node()
            executor = make_executor()
        except ConfigError as e:
            print(f"[{name}] invalid configuration: {e}", file=sys.stderr, flush=True)
            return EXIT_CONFIG_ERROR
        # what start-up loaded (modules, compiled kernels, the node) lives as long as the
        # process: out of the collector's reach, a full collection no longer walks its ~160k
        # objects (long enough to make a frame set late, in the association node)
        gc.collect()
        gc.freeze()
        executor.add_node(node)
        done = until(node) if until is not None else None
        try:
            spin_slices(executor, lambda: stop.is_set() or (done is not None and done.done()), done)
        finally:
            executor.shutdown(timeout_sec=1.0)
        if done is not None and done.done():
            return int(done.result())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        shutdown_ros(node)
    return 0
