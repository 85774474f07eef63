"""maem-record: record live topics into a rosbag2 (MCAP) bag, closed cleanly on SIGINT/SIGTERM.

Crash-safe (bagio.writer): chunks reach the disk at least every --chunk-duration s, metadata.yaml
is rewritten atomically at the start, on every split and every few seconds, so a killed
recorder loses about the last second and leaves a bag every reader opens (``maem-bag recover``
makes it whole). --max-bag-duration / --max-bag-size split the recording into files like
rosbag2; the same settings are ROS parameters (``-p max_bag_duration:=60``; a flag wins). A
full disk stops the recorder with one line saying what the bag holds (exit code 1).

Subscriptions take the serialized CDR bytes (raw=True) and write them unchanged; log time is the
receive time on the node clock (as rosbag2 does). A message lost before the recorder took it
(its subscription queue, keep last RECORD_DEPTH, overflowed while it was behind, or lost in
transport) shows as a gap in the publisher's sequence numbers: counted per topic in
/diagnostics (``dropped/dds_lost/<topic>``, ros/intake.py) and in the last line. Topic types
come from the ROS graph, polled until every requested topic is found (late publishers are
picked up). The subscription QoS follows the publishers: best effort if any publisher is,
transient local if all are.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from maem_ros import bagio
from maem_ros.bagio import WriteOptions
from maem_ros.ros.cli import EXIT_BAD_INPUT, init_ros, shutdown_ros, split_ros_args, stop_on_signals

if TYPE_CHECKING:  # rclpy is imported when the recorder runs (the CLI parses without it)
    from rclpy.qos import QoSProfile

    from maem_ros.ros.diagnostics import Diagnostics

_HIDDEN = ("/rosout", "/parameter_events")


@dataclass
class RecordOptions:
    out: str
    topics: list[str]
    all_maem: bool = False
    all_topics: bool = False
    duration_s: float = 0.0
    discovery_timeout_s: float = 10.0
    poll_s: float = 0.5
    write_flags: dict[str, Any] = field(default_factory=dict)  # WriteOptions given as flags


def parse_args(argv: Sequence[str]) -> RecordOptions:
    p = argparse.ArgumentParser(
        prog="maem-record",
        description="Record live topics into an MCAP rosbag2 bag "
        "(serialized bytes; closed cleanly on SIGINT/SIGTERM).",
    )
    p.add_argument("out", help="output bag folder (must not exist)")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="topics to record")
    p.add_argument("--all-maem", action="store_true", help="every /maem/* topic and /tf_static")
    p.add_argument(
        "--all",
        dest="all_topics",
        action="store_true",
        help="every topic except /rosout and /parameter_events",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=0.0,
        metavar="S",
        help="stop after S seconds (default: until SIGINT)",
    )
    p.add_argument(
        "--discovery-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="warn about requested topics not seen after S seconds (polling goes on)",
    )
    for spec in WriteOptions.specs():  # one definition: the ROS parameters use the same specs
        flag = "--" + spec.name.replace("_", "-")
        extra = f" [{spec.constraints()}]" if spec.constraints() else ""
        if spec.ptype is bool:
            p.add_argument(flag, action="store_true", default=None, help=spec.description)
        else:
            unit = spec.description.split(",")[0]  # "s, ..." / "MB, ..."
            p.add_argument(
                flag,
                type=spec.ptype,
                default=None,
                metavar=unit.upper(),
                help=f"{spec.description} (default {spec.default:g}){extra}",
            )
    a = p.parse_args(list(argv))
    if not (a.topics or a.all_maem or a.all_topics):
        p.error("nothing to record: give --topics, --all-maem or --all")
    for t in a.topics:
        if not t.startswith("/"):
            p.error(f"--topics: {t!r} must be an absolute topic name (start with '/')")
    flags = {s.name: getattr(a, s.name) for s in WriteOptions.specs() if getattr(a, s.name) is not None}
    try:
        WriteOptions(**flags)
    except ValueError as e:
        p.error(f"--{str(e).replace('_', '-')}")
    return RecordOptions(
        out=a.out,
        topics=list(dict.fromkeys(a.topics)),
        all_maem=a.all_maem,
        all_topics=a.all_topics,
        duration_s=max(0.0, a.duration),
        discovery_timeout_s=a.discovery_timeout,
        write_flags=flags,
    )


def wanted(topic: str, opts: RecordOptions) -> bool:
    if topic in opts.topics:
        return True
    if opts.all_maem and (topic.startswith("/maem/") or topic == "/tf_static"):
        return True
    return opts.all_topics and topic not in _HIDDEN


#: messages each recorder subscription holds (keep last). Unlike the live nodes (core.backlog)
#: the recorder never skips a message for being late: a recording wants every message and
#: nothing downstream waits for it, so a recorder that falls behind (a slow disk, a CPU stall)
#: writes the backlog late instead; this depth bounds that backlog's memory: ~3 s of a 30 fps
#: stream, 1.7 s at 60 fps, after which the oldest are overwritten (counted: Recorder.lost)
RECORD_DEPTH = 100
#: /diagnostics period of the recorder, s
DIAGNOSTICS_PERIOD_S = 1.0


def subscription_qos(publishers) -> QoSProfile:  # noqa: F821 - rclpy imported lazily
    """Match the publishers: best effort if any is, transient local if all are; keep last
    RECORD_DEPTH."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    best_effort = any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers)
    latched = bool(publishers) and all(
        p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers
    )
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=RECORD_DEPTH,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class Recorder:
    """Graph polling + raw subscriptions writing into a BagWriter (single-threaded executor);
    /diagnostics: per topic ``received/<topic>`` and ``dropped/dds_lost/<topic>`` (messages
    the publisher sent that never reached the bag), ``frames_processed`` = messages written."""

    def __init__(self, node, opts: RecordOptions, writer: bagio.BagWriter):
        from maem_ros.ros.diagnostics import Diagnostics

        self.node, self.opts, self.writer = node, opts, writer
        self.diag: Diagnostics = Diagnostics(node, DIAGNOSTICS_PERIOD_S, "maem_record")
        self.subs: dict[str, object] = {}
        self.rejected: dict[str, str] = {}
        self.received = 0
        self.t_start = time.monotonic()
        self.warned_missing = False
        self.error: bagio.BagWriteError | None = None

    def poll_graph(self) -> None:
        """Subscribe to newly visible wanted topics (first advertised type)."""
        from maem_ros.ros.intake import subscribe_counted
        from maem_ros.ros.player_node import message_class

        for topic, types in self.node.get_topic_names_and_types():
            if topic in self.subs or topic in self.rejected or not wanted(topic, self.opts):
                continue
            msgtype = types[0]
            try:
                if not bagio.known_type(msgtype):
                    raise ValueError(f"type {msgtype!r} is not in the ROS 2 Jazzy typestore")
                cls = message_class(msgtype)
                self.writer.add_topic(topic, msgtype, _bag_qos(self.node, topic))
            except ValueError as e:
                self.rejected[topic] = str(e)
                self.node.get_logger().error(f"topic {topic!r} not recorded: {e}")
                continue
            qos = subscription_qos(self.node.get_publishers_info_by_topic(topic))
            self.subs[topic] = subscribe_counted(
                self.node,
                self.diag,
                cls,
                topic,
                self._callback(topic, msgtype),
                qos,
                raw=True,
                lost_reason=_lost_reason(topic),
            )
            self.node.get_logger().info(f"recording {topic} [{msgtype}]")
        self._warn_missing()

    def _warn_missing(self) -> None:
        missing = [t for t in self.opts.topics if t not in self.subs and t not in self.rejected]
        if (
            missing
            and not self.warned_missing
            and time.monotonic() - self.t_start > self.opts.discovery_timeout_s
        ):
            self.warned_missing = True
            self.node.get_logger().warning(
                f"no publisher yet after {self.opts.discovery_timeout_s:.0f} s for {missing}; still waiting"
            )

    def _callback(self, topic: str, msgtype: str):
        def on_message(data: bytes) -> None:
            self.received += 1
            if self.error is not None:
                return
            try:
                self.writer.write_raw(topic, msgtype, data, self.node.get_clock().now().nanoseconds)
            except bagio.BagWriteError as e:
                self.error = e
                return
            self.diag.ok()

        return on_message

    def lost(self) -> dict[str, int]:
        """Messages lost per recorded topic (sequence gaps, see the module docstring)."""
        return {t: self.diag.dropped.get(_lost_reason(t), 0) for t in self.subs}

    def summary(self) -> str:
        """The last line: what was written, received and lost."""
        w = self.writer
        per_topic = ", ".join(f"{t}: {n}" for t, n in w.counts.items()) or "no topics"
        lost = {t: n for t, n in self.lost().items() if n}
        lost_text = f" ({', '.join(f'{t}: {n}' for t, n in lost.items())})" if lost else ""
        return (
            f"maem-record: wrote {w.message_count} messages to {self.opts.out} in "
            f"{len(w.files)} file(s) ({per_topic}); received {self.received}; lost before "
            f"the recorder took them: {sum(lost.values())}{lost_text}"
            f"{f'; not recorded: {sorted(self.rejected)}' if self.rejected else ''}"
        )

    def tick(self) -> None:
        """Timer: write the open chunk / metadata.yaml when due."""
        if self.error is None:
            try:
                self.writer.tick()
            except bagio.BagWriteError as e:
                self.error = e


def _lost_reason(topic: str) -> str:
    """The /diagnostics drop reason of ``topic``'s lost messages (dropped/dds_lost/<topic>)."""
    return f"dds_lost/{topic.lstrip('/')}"


def _bag_qos(node, topic: str):
    """Offered QoS recorded in the bag metadata: latched if all publishers are transient local."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    pubs = node.get_publishers_info_by_topic(topic)
    if pubs and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs):
        return bagio.QOS_LATCHED
    if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in pubs):
        return bagio.QOS_SENSOR
    return bagio.QOS_RELIABLE


def write_options(node, opts: RecordOptions) -> WriteOptions:
    """The node's WriteOptions parameters, overridden by the flags given (ConfigError, one
    line, on a bad parameter)."""
    from maem_ros.ros.params import declare_params

    values = declare_params(node, WriteOptions.specs())
    values.update(opts.write_flags)
    return WriteOptions(**values)


def _drain(executor, recorder: Recorder, max_s: float = 2.0) -> None:
    """Process callbacks already queued (until idle for 0.1 s or max_s)."""
    deadline = time.monotonic() + max_s
    idle_since = time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - idle_since < 0.1:
        before = recorder.received
        executor.spin_once(timeout_sec=0.02)
        if recorder.received != before:
            idle_since = time.monotonic()


def main(args: Sequence[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    ours, ros_args = split_ros_args(sys.argv if args is None else ["maem-record", *args])
    opts = parse_args(ours)
    stop = stop_on_signals("maem-record", grace_s=None)  # the bag is finalised whatever it takes
    # ROS first: a bad --ros-args must not leave a half-written bag behind
    if not init_ros(ros_args, "maem-record"):
        return EXIT_BAD_INPUT
    node = rclpy.create_node("maem_recorder")
    try:
        writer = bagio.BagWriter(opts.out, options=write_options(node, opts))
    except ValueError as e:  # ConfigError: a bad ROS parameter
        print(f"maem-record: {e}", file=sys.stderr)
        shutdown_ros(node)
        return EXIT_BAD_INPUT
    except OSError as e:  # exists already, no permission, full disk
        print(f"maem-record: output bag {opts.out!r}: {e.strerror or e}", file=sys.stderr)
        shutdown_ros(node)
        return EXIT_BAD_INPUT
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    rec = Recorder(node, opts, writer)
    try:
        rec.poll_graph()
        node.create_timer(opts.poll_s, rec.poll_graph)
        node.create_timer(min(0.1, writer.options.chunk_duration / 4), rec.tick)
        deadline = time.monotonic() + opts.duration_s if opts.duration_s else None
        while not stop.is_set() and rec.error is None and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
        if rec.error is None:
            _drain(executor, rec)
    finally:
        writer.close()
        # the bag is whole now: say so before the ROS teardown, which a stalled middleware
        # could keep from ever returning (the line is what the user needs)
        if rec.error is not None:
            print(f"maem-record: {rec.error.strerror}", file=sys.stderr, flush=True)
        else:
            print(rec.summary(), flush=True)
        executor.shutdown(timeout_sec=1.0)
        shutdown_ros(node)
    return 1 if rec.error is not None else 0


if __name__ == "__main__":
    sys.exit(main())
