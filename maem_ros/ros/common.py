"""Shared node plumbing: QoS profiles, validated parameters, /diagnostics, the main() runner.

QoS (chosen deliberately, see doc/design.md §4):
  * images: sensor data (best effort, keep last 2): a slow frontend drops stale frames instead of
    queueing them, and best-effort subscribers also accept reliable camera drivers.
  * detections / clusters / poses: reliable, keep last 10, volatile: every processed frame reaches
    the next stage while a short burst is buffered; no history for late joiners.
  * markers: reliable, keep last 10 (RViz default subscription QoS).
  * /diagnostics: reliable, keep last 10 (what diagnostic_aggregator expects).
"""
from __future__ import annotations

import gc
import inspect
import math
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import (
    InvalidHandle,
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from maem_ros.core.errors import InputError
from maem_ros.core.paramspec import ParamError, Params, ParamSpec, param
from maem_ros.ros.cli import init_ros, shutdown_ros, stop_on_signals

#: camera images: best effort, keep last 2
IMAGE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2,
                       reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
#: images from a replay that must arrive (maem-play --reliable-images): reliable, keep last 10
RELIABLE_IMAGE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                                reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.VOLATILE)
#: messages kept per per-frame stream (detections, clusters, poses) at both ends, writer and
#: reader: ~1 s at 30 fps, so a node starved of CPU for a while (a few hundred ms happen on a
#: loaded machine) finds every message of the stall still queued instead of overwritten
#: (dropped/dds_lost),
#: and the upstream node's backlog, sent as a burst afterwards, fits
DATA_DEPTH = 32


def data_qos(depth: int = DATA_DEPTH) -> QoSProfile:
    """Per-frame streams: reliable, keep last ``depth``, volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


DATA_QOS = data_qos()
#: MarkerArray for RViz: reliable, keep last 10
MARKER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
#: /tf_static: reliable, transient local, keep last 1 (what tf2's static broadcaster offers)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: /diagnostics: reliable, keep last 10
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)

#: exit code of a node whose parameters are invalid
EXIT_CONFIG_ERROR = 2


class ConfigError(ValueError):
    """A parameter value the node cannot start with (reported as one line, exit code 2)."""


# ---------------------------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------------------------
_PTYPE = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
          list: ParameterType.PARAMETER_STRING_ARRAY}


@dataclass
class NodeParams(Params):
    """Parameters every processing node has (node-only parameter classes subclass this)."""

    diagnostics_period: float = param(1.0, "s, /diagnostics publish period (steady clock)",
                                      minimum=0.0, exclusive_minimum=True)


def declare_params(node: Node, specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """Declare read-only parameters with descriptors; return {name: validated value}.

    Parameters are dynamically typed for rclpy and type-checked by ParamSpec.check, so an
    integer given for a double parameter (``tau_mesh: 8``) is accepted and converted. Any bad
    value raises ConfigError with one line naming the parameter.
    """
    out: dict[str, Any] = {}
    for spec in specs:
        desc = ParameterDescriptor(name=spec.name, type=_PTYPE[spec.ptype],
                                   description=spec.description,
                                   additional_constraints=spec.constraints(), read_only=True)
        try:
            if spec.ptype is list:  # rclpy cannot infer a type from [] (string arrays only)
                value = node.declare_parameter(spec.name, Parameter.Type.STRING_ARRAY, desc).value
                value = list(spec.default) if value is None else value
            else:
                desc.dynamic_typing = True
                value = node.declare_parameter(spec.name, spec.default, desc).value
        except InvalidParameterTypeException as e:
            raise ConfigError(f"parameter '{spec.name}': expected {spec.ptype.__name__} "
                              f"({_short(e)})") from None
        except (InvalidParameterValueException, ParameterException) as e:
            raise ConfigError(f"parameter '{spec.name}': {_short(e)}") from None
        try:
            out[spec.name] = spec.check(value)
        except ParamError as e:
            raise ConfigError(f"parameter '{e.name}': {e.problem}") from None
    return out


def _short(e: Exception) -> str:
    return " ".join(str(e).split())[:200]


def default_camera_name(node: Node) -> str:
    """The last component of the node's namespace ('' at the root namespace)."""
    return node.get_namespace().rstrip("/").rsplit("/", 1)[-1]


# ---------------------------------------------------------------------------------------------
# diagnostics
# ---------------------------------------------------------------------------------------------
@dataclass
class _Stage:
    samples: deque = field(default_factory=lambda: deque(maxlen=200))

    def summary(self) -> tuple[float, float]:
        s = sorted(self.samples)
        if not s:
            return math.nan, math.nan
        return s[len(s) // 2], s[min(len(s) - 1, int(math.ceil(0.99 * len(s))) - 1)]


#: topics every node has that say nothing about the data graph (left out of the match counts)
_INFRA_TOPICS = frozenset({"/rosout", "/parameter_events", "/diagnostics"})


class Diagnostics:
    """Counters and timings of one node, published as a DiagnosticArray every ``period`` s.

    Values (KeyValue, all strings): ``rate_hz/<topic>`` input rate over the last period and
    ``received/<topic>`` messages received (topic without its leading slash),
    ``frames_processed``, ``frames_dropped``, ``dropped/<reason>`` cumulative counts,
    ``time_ms/<stage>/median`` and ``/p99`` over the last 200 samples, ``count/<name>``
    cumulative counters (gate rejections ...), ``missing/<camera>`` frame sets without it,
    ``matched_publishers/<topic>`` / ``matched_subscribers/<topic>`` DDS-matched endpoints of
    each subscription / publisher (see :meth:`connections`), plus free-form ``set(key, value)``
    entries and what each :meth:`add_source` returns. Level: WARN when frames were dropped or
    cameras missing during the last period or a source warns, else OK. Thread-safe.
    """

    def __init__(self, node: Node, period_s: float = 1.0, hardware_id: str = "maem_ros"):
        self._node = node
        self._lock = threading.Lock()
        self._hardware_id = hardware_id
        self._inputs: dict[str, int] = defaultdict(int)
        self._inputs_total: dict[str, int] = defaultdict(int)
        self.processed = 0
        self.dropped: dict[str, int] = defaultdict(int)
        self.counts: dict[str, float] = defaultdict(float)
        self.missing: dict[str, int] = defaultdict(int)
        self._stages: dict[str, _Stage] = defaultdict(_Stage)
        self._values: dict[str, str] = {}
        self._last_pub = time.monotonic()
        self._warn_dropped = 0
        self._warn_missing = 0
        self._last_log: dict[str, float] = {}
        self._suppressed: dict[str, int] = defaultdict(int)
        self._sources: list[Callable[[], tuple[Mapping[str, str], str | None]]] = []
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        # steady clock: with use_sim_time a ROS-time timer stalls whenever /clock does
        self._timer = node.create_timer(period_s, self.publish,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- recording --------------------------------------------------------------------------
    def input(self, topic: str) -> None:
        with self._lock:
            self._inputs[topic] += 1
            self._inputs_total[topic] += 1

    def ok(self, n: int = 1) -> None:
        with self._lock:
            self.processed += n

    def drop(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self.dropped[reason] += n
            self._warn_dropped += n

    def reject(self, reason: str, text: str, log_period_s: float = 1.0, n: int = 1) -> None:
        """Count ``n`` dropped frames under ``reason`` and log ``text`` as one warning line (at
        most one line per reason per ``log_period_s``; the next line says how many were
        suppressed)."""
        self.drop(reason, n)
        self.log_throttled(reason, f"dropped [{reason}] {text}", log_period_s, n)

    def log_throttled(self, key: str, text: str, log_period_s: float = 1.0, n: int = 1) -> None:
        """One warning line per ``key`` per ``log_period_s`` (the next says how many were
        suppressed)."""
        now = time.monotonic()
        with self._lock:
            if now - self._last_log.get(key, -math.inf) < log_period_s:
                self._suppressed[key] += n
                return
            self._last_log[key] = now
            skipped = self._suppressed.pop(key, 0)
        more = f" (+{skipped} more '{key}')" if skipped else ""
        self._node.get_logger().warning(f"{text}{more}")

    def count(self, name: str, n: float = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def add_counts(self, stats: Mapping[str, float], names: Iterable[str]) -> None:
        with self._lock:
            for k in names:
                if k in stats:
                    self.counts[k] += float(stats[k])

    def camera_missing(self, cameras: Iterable[str]) -> None:
        with self._lock:
            for c in cameras:
                self.missing[c] += 1
                self._warn_missing += 1

    def time(self, stage: str, ms: float) -> None:
        with self._lock:
            self._stages[stage].samples.append(float(ms))

    def set(self, key: str, value: Any) -> None:
        with self._lock:
            self._values[key] = str(value)

    def add_source(self, source: Callable[[], tuple[Mapping[str, str], str | None]]) -> None:
        """``source()`` is called at every publish: its values join the status, and its
        warning (a sentence, or None) is appended to the message and makes the level WARN
        (a state that lasts, such as a node being behind)."""
        self._sources.append(source)

    @property
    def total_dropped(self) -> int:
        with self._lock:
            return sum(self.dropped.values())

    # -- publishing ---------------------------------------------------------------------------
    def snapshot(self) -> dict[str, str]:
        """Current key/value pairs (what the next DiagnosticStatus will hold)."""
        now = time.monotonic()
        with self._lock:
            dt = max(now - self._last_pub, 1e-6)
            kv: dict[str, str] = {}
            for topic in sorted(self._inputs_total):
                name = topic.lstrip("/")
                kv[f"rate_hz/{name}"] = f"{self._inputs[topic] / dt:.2f}"
                kv[f"received/{name}"] = str(self._inputs_total[topic])
            kv["frames_processed"] = str(self.processed)
            kv["frames_dropped"] = str(sum(self.dropped.values()))
            for reason in sorted(self.dropped):
                kv[f"dropped/{reason}"] = str(self.dropped[reason])
            for name in sorted(self.counts):
                v = self.counts[name]
                kv[f"count/{name}"] = str(int(v)) if float(v).is_integer() else f"{v:.3f}"
            for cam in sorted(self.missing):
                kv[f"missing/{cam}"] = str(self.missing[cam])
            for stage in sorted(self._stages):
                med, p99 = self._stages[stage].summary()
                kv[f"time_ms/{stage}/median"] = f"{med:.3f}"
                kv[f"time_ms/{stage}/p99"] = f"{p99:.3f}"
            kv.update(self._values)
        kv.update(self.connections())
        return kv

    def connections(self) -> dict[str, str]:
        """``matched_publishers/<topic>`` for each of the node's subscriptions and
        ``matched_subscribers/<topic>`` for each publisher: endpoints matched at the DDS level,
        as this side sees them (the ROS graph lists a node before its endpoints are matched,
        and a message sent before both sides matched is lost). Infrastructure topics
        (/rosout, /parameter_events, /diagnostics) are left out."""
        kv: dict[str, str] = {}
        try:
            for sub in self._node.subscriptions:
                if sub.topic_name not in _INFRA_TOPICS:
                    kv[f"matched_publishers/{sub.topic_name.lstrip('/')}"] = \
                        str(sub.get_publisher_count())
            for pub in self._node.publishers:
                if pub.topic_name not in _INFRA_TOPICS:
                    kv[f"matched_subscribers/{pub.topic_name.lstrip('/')}"] = \
                        str(pub.get_subscription_count())
        except InvalidHandle:  # an endpoint destroyed during shutdown
            pass
        return kv

    def publish(self) -> None:
        kv = self.snapshot()
        with self._lock:
            dropped, missing = self._warn_dropped, self._warn_missing
            self._warn_dropped = self._warn_missing = 0
            self._inputs.clear()
            self._last_pub = time.monotonic()
        level, message = DiagnosticStatus.OK, f"{kv['frames_processed']} frames processed"
        if dropped or missing:
            level = DiagnosticStatus.WARN
            message += f"; last period: {dropped} dropped, {missing} missing camera slots"
        for source in self._sources:
            values, warning = source()
            kv.update(values)
            if warning:
                level = DiagnosticStatus.WARN
                message += f"; {warning}"
        status = DiagnosticStatus(level=level, name=self._node.get_fully_qualified_name(),
                                  message=message, hardware_id=self._hardware_id,
                                  values=[KeyValue(key=k, value=v) for k, v in kv.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        try:
            self._pub.publish(msg)
        except Exception:  # noqa: BLE001 - publishing during shutdown: context already invalid
            pass


class RejectErrors:
    """``with RejectErrors(diag, where, reason) as step:`` ... ``if step.failed: return``.

    One processing step of a callback: an InputError drops the frame under its own ``reason``,
    another ValueError (bad input the core refused) under ``reason``, any other Exception under
    ``internal_error`` (a bug must not stop the live graph; it is counted and logged), each with
    one log line starting with ``where``.
    """

    def __init__(self, diag: Diagnostics, where: str, reason: str):
        self._diag, self._where, self._reason = diag, where, reason
        self.failed = False

    def __enter__(self) -> RejectErrors:
        return self

    def __exit__(self, exc_type, e, tb) -> bool:
        if not isinstance(e, Exception):
            return False
        self.failed = True
        if isinstance(e, InputError):
            self._diag.reject(e.reason, f"{self._where}: {e}")
        elif isinstance(e, ValueError):
            self._diag.reject(self._reason, f"{self._where}: {e}")
        else:
            self._diag.reject("internal_error", f"{self._where}: {type(e).__name__}: {e}")
        return True


class SequenceGaps:
    """Messages a subscription never got: gaps in the publisher's sequence numbers.

    DDS keep-last history silently overwrites messages a slow node has not taken yet; the
    ``publication_sequence_number`` of the message info shows the gap. Counted only while the
    topic has one publisher: the message info does not say which publisher sent a message, so
    while several publish, their sequences interleave and nothing is counted, and once one is
    left the count starts again from its next message. A number going back is a restarted
    publisher, not a loss; the first message sets the start.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._shared = False  # several publishers seen since the last anchor

    def lost(self, info: Mapping[str, Any] | None, publishers: Callable[[], int]) -> int:
        seq = (info or {}).get("publication_sequence_number")
        if not isinstance(seq, int) or seq <= 0:
            return 0
        if self._shared:
            if publishers() > 1:
                self._last = seq
                return 0
            self._shared, self._last = False, None  # one publisher again: re-anchor
        last, self._last = self._last, seq
        if last is None or seq <= last + 1:
            return 0
        if publishers() > 1:
            self._shared = True
            return 0
        return seq - last - 1


def subscribe_counted(node: Node, diag: Diagnostics, msg_type: Any, topic: str,
                      callback: Callable[..., None], qos: QoSProfile, raw: bool = False,
                      with_info: bool = False):
    """create_subscription whose callback first records the input in ``diag`` and counts
    messages lost before the node took them (``dropped/dds_lost``, see SequenceGaps).

    ``raw``: the callback gets the serialized message (bytes), for decoders that read it in
    place (wire.cdr_to_cloud); ``with_info``: it gets ``(msg, info)``, the rmw message info
    (``received_timestamp`` etc., see :func:`arrival_ns`)."""
    gaps = SequenceGaps()
    sub = None

    def on_message(*taken: Any) -> None:
        # SingleThreadedExecutor and take_pending call (msg, info); rclpy's EventsExecutor
        # (Jazzy 7.1) passes the (msg, info) tuple as one argument
        msg, info = taken if len(taken) == 2 else taken[0]
        diag.input(topic)
        lost = gaps.lost(info, sub.get_publisher_count)  # type: ignore[attr-defined]  # set below
        if lost:
            diag.reject("dds_lost", f"{topic}: {lost} message(s) overwritten in the DDS history "
                        f"before this node took them (node too slow for the input rate)", n=lost)
        if with_info:
            callback(msg, info)
        else:
            callback(msg)

    # rclpy: a callback that wants the info
    on_message.__signature__ = _MSG_INFO_SIGNATURE  # type: ignore[attr-defined]
    sub = node.create_subscription(msg_type, topic, on_message, qos, raw=raw)
    return sub


_MSG_INFO_SIGNATURE = inspect.Signature(
    [inspect.Parameter(name, inspect.Parameter.POSITIONAL_ONLY) for name in ("msg", "info")])


def take_pending(sub, limit: int = 1000) -> int:
    """Run ``sub``'s callback on every sample already waiting in its DDS reader queue, now,
    without waiting (at most ``limit``); returns how many were taken.

    The executor takes one sample per subscription per wait and runs ready timers first, so a
    node busy with earlier work sees a timer before messages that arrived meanwhile. A node
    that decides on what it has received (the association's synchroniser: is a frame set
    complete, or has it waited long enough?) takes everything pending first."""
    taken = 0
    while taken < limit:
        try:
            with sub.handle:
                got = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:  # destroyed during shutdown
            return taken
        if got is None:
            return taken
        sub.callback(*got)
        taken += 1
    return taken


def arrival_ns(now_ns: int, info: Mapping[str, Any] | None) -> int:
    """When a message reached this process, on the caller's clock (``now_ns``): now minus the
    time it waited in the DDS queue, from the rmw ``received_timestamp`` (system clock, ns;
    ``now_ns`` itself when the rmw does not fill it in)."""
    received = (info or {}).get("received_timestamp")
    if not isinstance(received, int) or received <= 0:
        return int(now_ns)
    return int(now_ns) - max(0, time.time_ns() - received)


class Stopwatch:
    """``with Stopwatch(diag, "stage"):`` records the block's wall time in ms."""

    def __init__(self, diag: Diagnostics, stage: str):
        self._diag, self._stage = diag, stage

    def __enter__(self) -> Stopwatch:
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.ms = (time.perf_counter() - self._t0) * 1e3
        self._diag.time(self._stage, self.ms)


# ---------------------------------------------------------------------------------------------
# main()
# ---------------------------------------------------------------------------------------------
def print_help(name: str, doc: str | None, specs: Sequence[ParamSpec]) -> None:
    """``--help`` of a node: usage, the module docstring's first paragraph, every parameter
    with type, default, constraints and description."""
    summary = (doc or "").strip().split("\n\n", 1)[0].strip()
    lines = [f"usage: ros2 run maem_ros {name} [--ros-args [--params-file FILE] "
             f"[-p {name}:NAME:=VALUE] [-r __ns:=/NS] ...]", "", summary, "",
             "parameters (read-only, set at start):"]
    lines += [f"  {spec.help_line()}" for spec in specs]
    print("\n".join(lines), flush=True)


def wants_help(args: Sequence[str] | None) -> bool:
    """``-h``/``--help`` before any ``--ros-args``."""
    argv = list(sys.argv if args is None else args)[1:]
    if "--ros-args" in argv:
        argv = argv[:argv.index("--ros-args")]
    return "-h" in argv or "--help" in argv


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
    by ``MAEM_EXECUTOR``: ``single`` (default), rclpy's SingleThreadedExecutor, or ``events``,
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
        raise ConfigError(f"environment {EXECUTOR_VAR}={choice!r}: expected one of "
                          f"{list(EXECUTORS)}")
    if choice == "events":
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def spin_slices(executor, stop: Callable[[], bool], until: Future | None = None,
                slice_s: float = 0.1) -> None:
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
    ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    try:
        mb = int(os.environ.get(HEAP_PREFAULT_VAR, prefault_mb))
    except ValueError:
        value = os.environ[HEAP_PREFAULT_VAR]
        raise ConfigError(f"environment {HEAP_PREFAULT_VAR}={value!r}: expected MiB as an "
                          f"integer") from None
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


def run_node(make_node: Callable[[], Node], args: list[str] | None, name: str,
             until: Callable[[Node], Future] | None = None,
             specs: Sequence[ParamSpec] = (), doc: str | None = None,
             heap_prefault_mb: int = 0) -> int:
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
            spin_slices(executor, lambda: stop.is_set() or (done is not None and done.done()),
                        done)
        finally:
            executor.shutdown(timeout_sec=1.0)
        if done is not None and done.done():
            return int(done.result())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        shutdown_ros(node)
    return 0


def load_rig_param(value: str, name: str = "rig"):
    """The Rig named by a ``rig`` parameter (file, folder or shipped name); ConfigError if not."""
    from maem_ros.core.geometry.camera import Rig
    from maem_ros.params import resolve_rig_path

    if not value:
        raise ConfigError(f"parameter '{name}': required (rig YAML, camera-JSON folder or shipped "
                          f"rig name)")
    try:
        return Rig.load(resolve_rig_path(value))
    except (ValueError, OSError) as e:
        raise ConfigError(f"parameter '{name}': {e}") from None


def publish_rig_tf(node: Node, rig, world_frame: str):
    """Publish world -> every rig camera once on /tf_static (transient local, so late joiners
    get it); the publisher, or None with one log line when tf2_msgs is not importable (it is
    built by ``make``, see doc/design.md §4)."""
    from maem_ros.core.geometry.frames import rig_transforms
    from maem_ros.ros import wire

    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        node.get_logger().warning("TF skipped: tf2_msgs is not importable (make builds it from "
                                  "its upstream definition; see doc/design.md §4)")
        return None
    pub = node.create_publisher(TFMessage, wire.TF_STATIC_TOPIC, TF_STATIC_QOS)
    pub.publish(wire.tf_message(rig_transforms(rig, world_frame),
                                node.get_clock().now().nanoseconds))
    return pub
