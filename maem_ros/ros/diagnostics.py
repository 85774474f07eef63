"""/diagnostics of a node: counters, timings and drop reasons (Diagnostics), the per-step
error wrapper (RejectErrors) and a stage stopwatch."""

from __future__ import annotations

import math
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node

from maem_ros.core.errors import InputError
from maem_ros.ros.qos import DIAGNOSTICS_QOS


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
        self._timer = node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

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
                    kv[f"matched_publishers/{sub.topic_name.lstrip('/')}"] = str(sub.get_publisher_count())
            for pub in self._node.publishers:
                if pub.topic_name not in _INFRA_TOPICS:
                    kv[f"matched_subscribers/{pub.topic_name.lstrip('/')}"] = str(
                        pub.get_subscription_count()
                    )
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
        status = DiagnosticStatus(
            level=level,
            name=self._node.get_fully_qualified_name(),
            message=message,
            hardware_id=self._hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in kv.items()],
        )
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
