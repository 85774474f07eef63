"""maem-play: publish a rosbag2 (MCAP) bag with its original timing.

Messages are published as the serialized CDR bytes stored in the bag (no decode/re-encode).
Timing: message with log time t is published at wall time w0 + (t - t0) / rate.
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
from dataclasses import dataclass, field
from typing import Iterator, Sequence

from maem_ros import bagio
from maem_ros.ros.cli import EXIT_BAD_INPUT, init_ros, split_ros_args, stop_on_signals

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


def parse_args(argv: Sequence[str]) -> PlayOptions:
    p = argparse.ArgumentParser(
        prog="maem-play", description="Publish a rosbag2 bag's messages with the original timing "
        "(serialized bytes, per-topic QoS: images best effort, /maem/scene transient local, others "
        "reliable). Header stamps are not rewritten on --loop.")
    p.add_argument("bag", help="rosbag2 folder (metadata.yaml + .mcap)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="replay forever until SIGINT")
    p.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="start S seconds after the bag's first message")
    p.add_argument("--topics", nargs="+", metavar="TOPIC",
                   help="only these topics; shell-style patterns allowed, e.g. '/*/image_raw/*' "
                   "(default all)")
    p.add_argument("--exclude", nargs="+", default=[], metavar="TOPIC",
                   help="leave out these topics (patterns allowed, e.g. '/*/detections')")
    p.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO", help="rename topics")
    p.add_argument("--clock", nargs="?", type=float, const=40.0, default=None, metavar="HZ",
                   help="publish /clock (bag time) at HZ (default 40) for use_sim_time")
    p.add_argument("--delay", type=float, default=0.5, metavar="S",
                   help="wait S seconds after creating publishers (discovery; default 0.5)")
    p.add_argument("--wait-subscribers", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds until every publisher has a subscriber")
    p.add_argument("--wait-topics", nargs="+", default=[], metavar="TOPIC",
                   help="with --wait-subscribers: only these bag topics (patterns allowed) must have "
                   "a subscriber, e.g. '/*/image_raw/compressed' (default all)")
    p.add_argument("--min-subscribers", type=int, default=1, metavar="N",
                   help="with --wait-subscribers: wait until each awaited topic has N subscribers")
    a = p.parse_args(list(argv))
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
    return PlayOptions(bag=a.bag, rate=a.rate, loop=a.loop, start_s=a.start, topics=a.topics,
                       exclude=a.exclude,
                       remap=remap, clock=a.clock is not None, clock_hz=a.clock or 40.0,
                       delay_s=max(0.0, a.delay), wait_subscribers_s=max(0.0, a.wait_subscribers),
                       wait_topics=a.wait_topics, min_subscribers=max(1, a.min_subscribers))


def select_topics(available: Sequence[str], topics: Sequence[str] | None,
                  exclude: Sequence[str] = ()) -> tuple[list[str], list[str]]:
    """(selected topics in bag order, --topics patterns that matched nothing).

    Patterns are shell-style (fnmatch); a plain name matches only itself.
    """
    pats = list(topics) if topics is not None else ["*"]
    sel = [t for t in available if any(fnmatch.fnmatchcase(t, p) for p in pats)
           and not any(fnmatch.fnmatchcase(t, x) for x in exclude)]
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
        raise ValueError(f"message type {msgtype!r}: Python package {pkg!r} has no {kind}.{name} "
                         "(install its ROS message package)") from None


def topic_qos(topic: str, msgtype: str, recorded: Sequence = ()):
    """Publisher QoS: images as the camera nodes publish them (common.IMAGE_QOS, best effort);
    latched (transient local) for /maem/scene or when recorded so; everything else reliable,
    keep last 10."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from maem_ros.ros.common import IMAGE_QOS
    latched = topic == bagio.SCENE_TOPIC or any(
        q.durability == bagio.QosDurability.TRANSIENT_LOCAL for q in recorded)
    if latched:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if msgtype in _IMAGE_TYPES:
        return IMAGE_QOS
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


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
        self.wall0 = self.bag0 = None

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
            node.get_logger().warning(f"--topics: {t!r} matches no topic of the bag; known: "
                                      f"{sorted(self.info.topics)}")
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
            self.pubs[t] = node.create_publisher(cls, out, topic_qos(t, msgtype,
                                                                     self.info.qos.get(t, ())))
        self.clock_pub = None
        if opts.clock:
            from rosgraph_msgs.msg import Clock
            from rclpy.qos import QoSProfile
            self.clock_pub = node.create_publisher(Clock, "/clock", QoSProfile(depth=1))
        self.published = 0

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
        while (time.monotonic() < deadline and not self.stop.is_set()
               and any(p.get_subscription_count() < self.opts.min_subscribers for p in awaited)):
            self.stop.wait(0.02)
        if self.opts.delay_s:
            self.stop.wait(self.opts.delay_s)

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
        return bagio.read_messages(self.opts.bag, list(self.pubs), start_ns=start_ns)

    def _publish_latched_before(self, start_ns: int) -> None:
        """Latched topics (e.g. /maem/scene) recorded before --start are published first."""
        latched = [t for t in self.pubs if t == bagio.SCENE_TOPIC or any(
            q.durability == bagio.QosDurability.TRANSIENT_LOCAL for q in self.info.qos.get(t, ()))]
        if latched and start_ns > self.info.start_ns:
            for m in bagio.read_messages(self.opts.bag, latched, stop_ns=start_ns):
                self.pubs[m.topic].publish(m.data)
                self.published += 1

    def play(self) -> int:
        """Play (and loop); returns the number of messages published."""
        if not self.pubs:
            return 0
        start_ns = self.info.start_ns + int(round(self.opts.start_s * 1e9))
        if start_ns > self.info.end_ns:
            raise ValueError(f"--start: {self.opts.start_s} s is past the bag's end "
                             f"({(self.info.end_ns - self.info.start_ns) / 1e9:.3f} s)")
        self._publish_latched_before(start_ns)
        pacer = Pacer(self.opts.rate, self.stop, self.publish_clock if self.clock_pub else None,
                      1.0 / self.opts.clock_hz)
        gap = loop_gap_ns(self.info)
        wall0 = None
        while not self.stop.is_set():
            first = None
            last = start_ns
            for m in self._messages(start_ns):
                if first is None:
                    first = m.log_time_ns
                    pacer.anchor(first, wall0)
                if not pacer.wait_until(m.log_time_ns):
                    return self.published
                self.publish_clock(m.log_time_ns)
                self.pubs[m.topic].publish(m.data)
                self.published += 1
                last = m.log_time_ns
            if not self.opts.loop or first is None:
                break
            wall0 = pacer.wall_target(last + gap)  # next pass starts one period after the last
        return self.published


def main(args: Sequence[str] | None = None) -> int:
    import rclpy

    ours, ros_args = split_ros_args(sys.argv if args is None else ["maem-play", *args])
    opts = parse_args(ours)
    try:
        bagio.bag_info(opts.bag)  # a bad bag: one line before any ROS set-up
    except bagio.BagError as e:
        print(f"maem-play: {e}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    stop = stop_on_signals("maem-play")
    if not init_ros(ros_args, "maem-play"):
        return EXIT_BAD_INPUT
    node = rclpy.create_node("maem_player")
    log = node.get_logger()
    code = 0
    try:
        player = BagPlayer(node, opts, stop)
        if not player.pubs:
            raise ValueError(f"{opts.bag}: no topic to play (bag topics: {sorted(player.info.topics)})")
        log.info(f"playing {opts.bag}: {len(player.pubs)} topics, rate {opts.rate}"
                 f"{', loop' if opts.loop else ''}{', /clock' if opts.clock else ''}")
        player.wait_ready()
        t0 = time.monotonic()
        n = player.play()
        elapsed = time.monotonic() - t0
        if not stop.is_set() and not player.wait_delivered():
            log.warning("some reliable messages were not acknowledged by all subscribers")
        log.info(f"published {n} messages in {elapsed:.2f} s"
                 f"{' (interrupted)' if stop.is_set() else ''}"
                 f"{f'; skipped topics: {sorted(player.skipped)}' if player.skipped else ''}")
    except ValueError as e:  # BagError (damaged mid-file), --start past the end, no topic
        log.error(str(e))
        code = EXIT_BAD_INPUT
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
