"""maem-play: publish a rosbag2 (MCAP) bag with its original timing.

Messages are published as the serialized CDR bytes stored in the bag (no decode/re-encode).
Timing: message with log time t is published at wall time w0 + (t - t0) / rate.
--lockstep TOPIC...: after each camera frame (the images sharing one log time; in a bag played
without images, the /<cam>/detections sharing one) the player waits until every TOPIC
(patterns resolved on the live graph, any message type whose first field is a std_msgs/Header,
e.g. /maem/clusters) has delivered a message stamped at or after that frame's image stamp, at
most --lockstep-timeout s, then goes on at --rate from there: a bag replayed
into frontends slower than the recording loses no frame to queue overflow or sync timeouts, and a
replay faster than real time none to the nodes' overload policy (they never fall behind).
Without it a replay faster than real time (--rate > 1) says that live nodes skip the frames
they fall behind on unless run with ``keep_every_set: true``.
--reliable-images publishes the images reliable (keep last 10) instead of best effort, so a
frontend subscribing reliable (image_reliability: reliable) receives every one.
Looping replays the same bytes, so header stamps are NOT rewritten: they jump back at each
loop start (the association node resets its queues when stamps go backwards). With --clock,
/clock follows bag log time (also jumping back on loop) for nodes run with use_sim_time.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

from maem_ros import bagio
from maem_ros.ros.cli import EXIT_BAD_INPUT, init_ros, shutdown_ros, split_ros_args, stop_on_signals

_IMAGE_TYPES = (bagio.IMAGE, bagio.COMPRESSED_IMAGE)


@dataclass
class PlayOptions:
    bag: str
    rate: float = 1.0
    loop: bool = False
    start_s: float = 0.0
    topics: list[str] | None = None
    exclude: list[str] = field(default_factory=list)
    remap: dict[str, str] = field(default_factory=dict)
    clock: bool = False
    clock_hz: float = 40.0
    delay_s: float = 0.5
    wait_subscribers_s: float = 0.0
    wait_topics: list[str] = field(default_factory=list)
    min_subscribers: int = 1
    lockstep: list[str] = field(default_factory=list)
    lockstep_timeout_s: float = 30.0
    reliable_images: bool = False


def _parser() -> argparse.ArgumentParser:
    """maem-play's options: what to play and how fast (_add_timing_options: when)."""
    p = argparse.ArgumentParser(
        prog="maem-play",
        description="Publish a rosbag2 bag's messages with the original timing "
        "(serialized bytes, per-topic QoS: images best effort, /maem/scene transient local, others "
        "reliable). Header stamps are not rewritten on --loop.",
    )
    p.add_argument("bag", help="rosbag2 folder (metadata.yaml + .mcap)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="replay forever until SIGINT")
    p.add_argument(
        "--start", type=float, default=0.0, metavar="S", help="start S seconds after the bag's first message"
    )
    p.add_argument(
        "--topics",
        nargs="+",
        metavar="TOPIC",
        help="only these topics; shell-style patterns allowed, e.g. '/*/image_raw/*' (default all)",
    )
    p.add_argument(
        "--exclude",
        nargs="+",
        default=[],
        metavar="TOPIC",
        help="leave out these topics (patterns allowed, e.g. '/*/detections')",
    )
    p.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO", help="rename topics")
    p.add_argument(
        "--clock",
        nargs="?",
        type=float,
        const=40.0,
        default=None,
        metavar="HZ",
        help="publish /clock (bag time) at HZ (default 40) for use_sim_time",
    )
    _add_timing_options(p)
    return p


def _add_timing_options(p: argparse.ArgumentParser) -> None:
    """maem-play's options for when to start and how to pace against the graph."""
    p.add_argument(
        "--delay",
        type=float,
        default=0.5,
        metavar="S",
        help="wait S seconds after creating publishers (discovery; default 0.5)",
    )
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds until every publisher has a subscriber",
    )
    p.add_argument(
        "--wait-topics",
        nargs="+",
        default=[],
        metavar="TOPIC",
        help="with --wait-subscribers: only these bag topics (patterns allowed) must have "
        "a subscriber, e.g. '/*/image_raw/compressed' (default all)",
    )
    p.add_argument(
        "--min-subscribers",
        type=int,
        default=1,
        metavar="N",
        help="with --wait-subscribers: wait until each awaited topic has N subscribers",
    )
    p.add_argument(
        "--lockstep",
        nargs="+",
        default=[],
        metavar="TOPIC",
        help="after each camera frame wait until every TOPIC (patterns allowed, "
        "matched on the live graph, e.g. /maem/clusters) has a message stamped at or "
        "after the frame, at most --lockstep-timeout s",
    )
    p.add_argument(
        "--lockstep-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="with --lockstep: longest wait per frame (default 30 s)",
    )
    p.add_argument(
        "--reliable-images",
        action="store_true",
        help="publish images reliable, keep last 10 (default best effort, keep last 2)",
    )


def parse_args(argv: Sequence[str]) -> PlayOptions:
    """maem-play's command line as PlayOptions (argparse error, exit 2, on a bad value)."""
    p = _parser()
    a = p.parse_args(list(argv))
    if not a.lockstep_timeout > 0:
        p.error(f"--lockstep-timeout: must be > 0, got {a.lockstep_timeout}")
    if not a.rate > 0:
        p.error(f"--rate: must be > 0, got {a.rate}")
    if a.start < 0:
        p.error(f"--start: must be >= 0, got {a.start}")
    if a.clock is not None and not a.clock > 0:
        p.error(f"--clock: frequency must be > 0, got {a.clock}")
    remap = {}
    for r in a.remap:
        src, sep, dst = r.partition(":=")
        if not sep or not src or not dst:
            p.error(f"--remap: expected FROM:=TO, got {r!r}")
        remap[src] = dst
    return PlayOptions(
        bag=a.bag,
        rate=a.rate,
        loop=a.loop,
        start_s=a.start,
        topics=a.topics,
        exclude=a.exclude,
        remap=remap,
        clock=a.clock is not None,
        clock_hz=a.clock or 40.0,
        delay_s=max(0.0, a.delay),
        wait_subscribers_s=max(0.0, a.wait_subscribers),
        wait_topics=a.wait_topics,
        min_subscribers=max(1, a.min_subscribers),
        lockstep=a.lockstep,
        lockstep_timeout_s=a.lockstep_timeout,
        reliable_images=a.reliable_images,
    )


def select_topics(
    available: Sequence[str], topics: Sequence[str] | None, exclude: Sequence[str] = ()
) -> tuple[list[str], list[str]]:
    """(selected topics in bag order, --topics patterns that matched nothing).

    Patterns are shell-style (fnmatch); a plain name matches only itself.
    """
    pats = list(topics) if topics is not None else ["*"]
    sel = [
        t
        for t in available
        if any(fnmatch.fnmatchcase(t, p) for p in pats)
        and not any(fnmatch.fnmatchcase(t, x) for x in exclude)
    ]
    unmatched = [p for p in pats if not any(fnmatch.fnmatchcase(t, p) for t in available)]
    return sel, unmatched


def message_class(msgtype: str):
    """Python message class for 'pkg/msg/Name' (importlib; no rosidl_runtime_py)."""
    pkg, kind, name = (msgtype.split("/") + ["", ""])[:3]
    if not (pkg and kind and name):
        raise ValueError(f"message type {msgtype!r}: expected 'package/msg/Name'")
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError):
        raise ValueError(
            f"message type {msgtype!r}: Python package {pkg!r} has no {kind}.{name} "
            "(install its ROS message package)"
        ) from None


def topic_qos(topic: str, msgtype: str, recorded: Sequence = (), reliable_images: bool = False):
    """Publisher QoS: images as the camera nodes publish them (common.IMAGE_QOS, best effort;
    ``reliable_images``: reliable, keep last 10); latched (transient local) for /maem/scene or
    when recorded so; everything else as the nodes publish it (common.DATA_QOS)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from maem_ros.ros.qos import DATA_QOS, IMAGE_QOS, RELIABLE_IMAGE_QOS

    latched = topic == bagio.SCENE_TOPIC or any(
        q.durability == bagio.QosDurability.TRANSIENT_LOCAL for q in recorded
    )
    if latched:
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
    if msgtype in _IMAGE_TYPES:
        return RELIABLE_IMAGE_QOS if reliable_images else IMAGE_QOS
    return DATA_QOS


def loop_gap_ns(info: bagio.BagInfo) -> int:
    """Pause between loop passes: one period of the most frequent topic (0 if unknown)."""
    n = max(info.counts.values(), default=0)
    return (info.end_ns - info.start_ns) // (n - 1) if n > 1 else 0


class Pacer:
    """Wall-clock pacing of bag time: sleep until wall time matches bag time / rate.

    ``wait_until`` returns False when ``stop`` is set. ``tick(bag_ns)`` is called while waiting
    (at most every ``tick_s``) so /clock can follow bag time.
    """

    def __init__(self, rate: float, stop: threading.Event, tick=None, tick_s: float = 0.025):
        self.rate, self.stop, self.tick, self.tick_s = rate, stop, tick, tick_s
        # both set by anchor() before the first wait
        self.wall0: int = None  # type: ignore[assignment]  # anchor() sets it before any use
        self.bag0: int = None  # type: ignore[assignment]  # as wall0

    def anchor(self, bag_ns: int, wall_ns: int | None = None) -> None:
        self.bag0, self.wall0 = bag_ns, time.monotonic_ns() if wall_ns is None else wall_ns

    def wall_target(self, bag_ns: int) -> int:
        return self.wall0 + int(round((bag_ns - self.bag0) / self.rate))

    def wait_until(self, bag_ns: int) -> bool:
        target = self.wall_target(bag_ns)
        while not self.stop.is_set():
            now = time.monotonic_ns()
            if now >= target:
                return True
            if self.tick is not None:
                self.tick(self.bag0 + int((now - self.wall0) * self.rate))
                step = min((target - now) / 1e9, self.tick_s)
            else:
                step = (target - now) / 1e9
            self.stop.wait(step)
        return False


class BagPlayer:
    """Publishes one bag on a node (publishers created up front, one per topic)."""

    def __init__(self, node, opts: PlayOptions, stop: threading.Event):
        self.node, self.opts, self.stop = node, opts, stop
        self.info = bagio.bag_info(opts.bag)
        self.topics, unknown = select_topics(list(self.info.topics), opts.topics, opts.exclude)
        for t in unknown:
            node.get_logger().warning(
                f"--topics: {t!r} matches no topic of the bag; known: {sorted(self.info.topics)}"
            )
        self.pubs = {}
        self.skipped: dict[str, str] = {}
        for t in self.topics:
            msgtype = self.info.topics[t]
            try:
                cls = message_class(msgtype)
            except ValueError as e:
                self.skipped[t] = str(e)
                node.get_logger().error(f"topic {t!r} skipped: {e}")
                continue
            out = opts.remap.get(t, t)
            self.pubs[t] = node.create_publisher(
                cls, out, topic_qos(t, msgtype, self.info.qos.get(t, ()), opts.reliable_images)
            )
        self.clock_pub = None
        if opts.clock:
            from rclpy.qos import QoSProfile
            from rosgraph_msgs.msg import Clock

            self.clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
        self.published = 0
        self.lockstep: Lockstep | None = None
        self.frame_topics = lockstep_frame_topics(self.info.topics, list(self.pubs))

    def publish_clock(self, bag_ns: int) -> None:
        if self.clock_pub is not None:
            from rosgraph_msgs.msg import Clock

            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
            self.clock_pub.publish(msg)

    def wait_ready(self) -> None:
        """Discovery: wait for subscribers (optional, bounded) then the fixed delay."""
        deadline = time.monotonic() + self.opts.wait_subscribers_s
        pats = self.opts.wait_topics or ["*"]
        awaited = [p for t, p in self.pubs.items() if any(fnmatch.fnmatchcase(t, x) for x in pats)]
        # best-effort images published before a subscriber is matched are simply lost
        while (
            time.monotonic() < deadline
            and not self.stop.is_set()
            and any(p.get_subscription_count() < self.opts.min_subscribers for p in awaited)
        ):
            self.stop.wait(0.02)
        if self.opts.delay_s:
            self.stop.wait(self.opts.delay_s)
        if self.opts.lockstep:
            self.lockstep = Lockstep(self.node, self.opts.lockstep, self.stop)

    def wait_delivered(self, timeout_s: float = 3.0) -> bool:
        """Before exiting: wait (bounded) until subscribers acknowledged every reliable message,
        so the last large messages are not lost when the process ends."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout_s
        ok = True
        for pub in self.pubs.values():
            left = max(0.0, deadline - time.monotonic())
            ok &= pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
        return ok

    def _messages(self, start_ns: int) -> Iterator[bagio.BagMessage]:
        return bagio.read_messages(self.opts.bag, list(self.pubs), start_ns=start_ns, info=self.info)

    def _publish_latched_before(self, start_ns: int) -> None:
        """Latched topics (e.g. /maem/scene) recorded before --start are published first."""
        latched = [
            t
            for t in self.pubs
            if t == bagio.SCENE_TOPIC
            or any(q.durability == bagio.QosDurability.TRANSIENT_LOCAL for q in self.info.qos.get(t, ()))
        ]
        if latched and start_ns > self.info.start_ns:
            for m in bagio.read_messages(self.opts.bag, latched, stop_ns=start_ns, info=self.info):
                self.pubs[m.topic].publish(m.data)
                self.published += 1

    def play(self) -> int:
        """Play (and loop); returns the number of messages published."""
        if not self.pubs:
            return 0
        start_ns = self.info.start_ns + int(round(self.opts.start_s * 1e9))
        if start_ns > self.info.end_ns:
            raise ValueError(
                f"--start: {self.opts.start_s} s is past the bag's end "
                f"({(self.info.end_ns - self.info.start_ns) / 1e9:.3f} s)"
            )
        self._publish_latched_before(start_ns)
        pacer = Pacer(
            self.opts.rate,
            self.stop,
            self.publish_clock if self.clock_pub else None,
            1.0 / self.opts.clock_hz,
        )
        gap = loop_gap_ns(self.info)
        wall0 = None
        while not self.stop.is_set():
            first = None
            last = start_ns
            frame: tuple[int, int] | None = None  # (log time, image stamp) of the last images
            if self.lockstep is not None:
                self.lockstep.restart()  # a loop pass replays the same stamps
            for m in self._messages(start_ns):
                if first is None:
                    first = m.log_time_ns
                    pacer.anchor(first, wall0)
                if frame is not None and m.log_time_ns > frame[0]:
                    if self.lockstep is not None:
                        self.lockstep.wait(frame[1], self.opts.lockstep_timeout_s)
                        pacer.anchor(m.log_time_ns)  # go on at --rate from here
                    frame = None
                if not pacer.wait_until(m.log_time_ns):
                    return self.published
                self.publish_clock(m.log_time_ns)
                self.pubs[m.topic].publish(m.data)
                self.published += 1
                last = m.log_time_ns
                if self.lockstep is not None and m.topic in self.frame_topics:
                    frame = (m.log_time_ns, _stamp_ns(m.data))
            if frame is not None and self.lockstep is not None:  # the last frame too
                self.lockstep.wait(frame[1], self.opts.lockstep_timeout_s)
            if not self.opts.loop or first is None:
                break
            wall0 = pacer.wall_target(last + gap)  # next pass starts one period after the last
        return self.published


def lockstep_frame_topics(bag_topics: dict[str, str], played: Sequence[str]) -> set[str]:
    """The played topics whose messages make up a camera frame for --lockstep: the images, or
    in a replay without images the per-camera detections (PointCloud2 ``*/detections``)."""
    images = {t for t in played if bag_topics[t] in _IMAGE_TYPES}
    return images or {t for t in played if bag_topics[t] == bagio.POINT_CLOUD2 and t.endswith("/detections")}


def _stamp_ns(data: bytes) -> int:
    from maem_ros.ros.wire import cdr_header_stamp_ns

    return cdr_header_stamp_ns(bytes(data))


class Lockstep:
    """Waits until every topic matching the patterns delivered a message stamped at or after a
    given stamp (raw subscriptions: only the CDR header stamp is read; spun in a thread)."""

    def __init__(self, node, patterns: Sequence[str], stop: threading.Event):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.node, self.stop = node, stop
        self.latest: dict[str, int] = {}
        self.cond = threading.Condition()
        self.timeouts = 0
        graph = dict(node.get_topic_names_and_types())
        self.topics = sorted(t for t in graph if any(fnmatch.fnmatchcase(t, p) for p in patterns))
        missing = [p for p in patterns if not any(fnmatch.fnmatchcase(t, p) for t in graph)]
        if missing:
            raise ValueError(
                f"--lockstep: {missing} match no topic on the graph (is the "
                f"consumer running?); topics: {sorted(graph)}"
            )
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.subs = [
            node.create_subscription(message_class(graph[t][0]), t, self._on(t), qos, raw=True)
            for t in self.topics
        ]
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self._done = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not (self._done.is_set() or self.stop.is_set()):
            self.executor.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        """Stop the spin thread (before the node is destroyed)."""
        self._done.set()
        self.thread.join(timeout=5.0)
        self.executor.remove_node(self.node)

    def _on(self, topic: str):
        def callback(data: bytes) -> None:
            try:
                stamp = _stamp_ns(data)
            except ValueError:
                return  # not header-first: never counts as delivered
            with self.cond:
                self.latest[topic] = max(stamp, self.latest.get(topic, -1))
                self.cond.notify_all()

        return callback

    def restart(self) -> None:
        """Forget the stamps seen (the bag starts again from its first frame)."""
        with self.cond:
            self.latest.clear()

    def wait(self, stamp_ns: int, timeout_s: float) -> bool:
        """True when every topic reached ``stamp_ns``; False on timeout (counted) or stop."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while not all(self.latest.get(t, -1) >= stamp_ns for t in self.topics):
                left = deadline - time.monotonic()
                if left <= 0 or self.stop.is_set():
                    self.timeouts += not self.stop.is_set()
                    if not self.stop.is_set():
                        late = [t for t in self.topics if self.latest.get(t, -1) < stamp_ns]
                        self.node.get_logger().warning(
                            f"--lockstep: no message stamped >= {stamp_ns} on {late} within "
                            f"{timeout_s:g} s; going on"
                        )
                    return False
                self.cond.wait(min(left, 0.1))
        return True


def main(args: Sequence[str] | None = None) -> int:
    import rclpy

    ours, ros_args = split_ros_args(sys.argv if args is None else ["maem-play", *args])
    opts = parse_args(ours)
    try:
        info = bagio.bag_info(opts.bag)  # a bad bag: one line before any ROS set-up
    except bagio.BagError as e:
        print(f"maem-play: {e}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    if info.damage:  # cut short by a crash: every complete message is played
        print(f"maem-play: warning: {info.damage}", file=sys.stderr, flush=True)
    stop = stop_on_signals("maem-play")
    if not init_ros(ros_args, "maem-play"):
        return EXIT_BAD_INPUT
    node = rclpy.create_node("maem_player")
    log = node.get_logger()
    code = 0
    player = None
    try:
        player = BagPlayer(node, opts, stop)
        if not player.pubs:
            raise ValueError(f"{opts.bag}: no topic to play (bag topics: {sorted(player.info.topics)})")
        log.info(
            f"playing {opts.bag}: {len(player.pubs)} topics, rate {opts.rate}"
            f"{', loop' if opts.loop else ''}{', /clock' if opts.clock else ''}"
        )
        if opts.rate > 1 and not opts.lockstep:
            log.warning(
                f"rate {opts.rate:g}: faster than real time, live nodes skip the frames "
                f"they fall behind on (counted dropped/behind); to process every frame "
                f"use --lockstep or run them with keep_every_set:=true"
            )
        player.wait_ready()
        t0 = time.monotonic()
        n = player.play()
        elapsed = time.monotonic() - t0
        if not stop.is_set() and not player.wait_delivered():
            log.warning("some reliable messages were not acknowledged by all subscribers")
        if player.lockstep is not None:
            log.info(
                f"lockstep on {player.lockstep.topics}: {player.lockstep.timeouts} "
                f"frame(s) timed out; every frame waited for the graph, so no node fell "
                f"behind and skipped one"
            )
        log.info(
            f"published {n} messages in {elapsed:.2f} s"
            f"{' (interrupted)' if stop.is_set() else ''}"
            f"{f'; skipped topics: {sorted(player.skipped)}' if player.skipped else ''}"
        )
    except ValueError as e:  # BagError (damaged mid-file), --start past the end, no topic
        log.error(str(e))
        code = EXIT_BAD_INPUT
    finally:
        if player is not None and player.lockstep is not None:
            player.lockstep.close()
        shutdown_ros(node)
    return code


if __name__ == "__main__":
    sys.exit(main())
