"""maem-foxglove: a live Foxglove view (WebSocket, foxglove-sdk) of the graph or of a bag.

    maem-foxglove --bag BAG [--bag BAG2 ...] [--port P] [--loop] [--rate R]   # no ROS graph
    maem-foxglove --ros-args -p rig:=sportcenter6                             # the live graph

With ``--bag`` the bags' messages are replayed into the Foxglove server with their recorded
timing (``--rate`` times real time, ``--loop`` to repeat): ``--topic`` (default /maem/poses;
/maem/gt_poses for the ground truth of maem-make-bag bags), /<cam>/image_raw/compressed or
/<cam>/image_raw, and /<cam>/camera_info for every camera of the rig. Several bags are merged
by log time (e.g. the demo bag's images with the poses a maem-record run wrote). The rig comes
from ``--rig`` or the first bag whose metadata holds one (maem-make-bag writes it). Playback
starts when the first client subscribes (``--no-wait``: at once). Without ``--bag`` this is the
live node ``ros2 run maem_ros foxglove`` (see maem_ros/ros/foxglove_node.py).

Open Foxglove, "Open connection", ws://127.0.0.1:8765 (the default address). Channels:
see maem_ros/viz/bridge.py. Bad inputs: one line naming the input, exit 2.
"""

from __future__ import annotations

import argparse
import heapq
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from maem_ros import bagio
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.skeleton import CONVENTIONS
from maem_ros.tools.cli import fail
from maem_ros.viz.scene import camera_info_fields


class InputError(ValueError):
    """A bad input: one line naming it (exit 2)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-foxglove",
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--bag",
        action="append",
        required=True,
        help="rosbag2 folder to replay (repeat to merge several by log time)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765; 0 = a free one)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="replay again and again until Ctrl-C")
    p.add_argument("--topic", default="/maem/poses", help="poses topic (default /maem/poses)")
    p.add_argument(
        "--rig", help="rig YAML, camera-JSON folder or shipped rig name (default: from the bag's metadata)"
    )
    p.add_argument(
        "--court",
        type=float,
        nargs=2,
        default=(28.0, 15.0),
        metavar=("L", "W"),
        help="court floor size in m (default 28 15)",
    )
    p.add_argument(
        "--convention",
        choices=sorted(CONVENTIONS),
        help="keypoint convention of the poses (default: the one with J joints)",
    )
    p.add_argument(
        "--frame",
        default="world",
        help="the rig's world frame: parent of the camera transforms (default world)",
    )
    p.add_argument(
        "--no-wait", action="store_true", help="start replaying at once instead of at the first subscription"
    )
    return p


def load_rig(args: argparse.Namespace) -> Rig:
    """--rig, else the rig YAML in the first bag's metadata that has one."""
    from maem_ros.params import resolve_rig_path

    if args.rig:
        try:
            return Rig.load(resolve_rig_path(args.rig))
        except (ValueError, OSError) as e:
            raise InputError(f"--rig {args.rig!r}: {e}") from None
    for bag in args.bag:
        try:
            text = bagio.read_rig_yaml(bag)
        except (ValueError, OSError) as e:
            raise InputError(str(e)) from None
        if text:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "rig.yaml"
                path.write_text(text)
                try:
                    return Rig.from_yaml(path)
                except ValueError as e:
                    raise InputError(f"bag {bag!r}: rig in metadata: {e}") from None
    raise InputError(f"bag {args.bag[0]!r}: no rig in metadata ({bagio.CUSTOM_RIG}); pass --rig")


class BagSource:
    """The bags' messages for the Foxglove bridge, merged by log time."""

    def __init__(self, bags: Sequence[str], rig: Rig, poses_topic: str, log=print):
        self.bags = list(bags)
        self.poses_topic = poses_topic
        infos = {}
        for b in self.bags:
            try:
                infos[b] = bagio.bag_info(b)
            except (ValueError, OSError) as e:
                raise InputError(str(e)) from None
        self.topics: dict[str, str] = {}
        for info in infos.values():
            self.topics.update(info.topics)
        self.camera_of: dict[str, tuple[str, str]] = {}  # topic -> (camera, kind)
        for cam in rig.names:
            for kind, topic in (
                ("compressed", f"/{cam}/image_raw/compressed"),
                ("raw", f"/{cam}/image_raw"),
                ("info", f"/{cam}/camera_info"),
            ):
                if topic in self.topics:
                    self.camera_of[topic] = (cam, kind)
        if poses_topic in self.topics and self.topics[poses_topic] != bagio.POINT_CLOUD2:
            raise InputError(
                f"bag {self.bags[0]!r}: topic {poses_topic!r} is "
                f"{self.topics[poses_topic]}, expected {bagio.POINT_CLOUD2}"
            )
        if poses_topic not in self.topics:
            log(
                f"no {poses_topic} in the bag(s): images only (--topic {bagio.GT_TOPIC} shows "
                "the ground truth of maem-make-bag bags)"
            )
        if not self.camera_of and poses_topic not in self.topics:
            raise InputError(
                f"bag {self.bags[0]!r}: neither {poses_topic} nor any camera topic "
                f"of the rig ({', '.join(rig.names)})"
            )
        self.wanted = [t for t in [poses_topic, *self.camera_of] if t in self.topics]

    def messages(self) -> Iterator:
        streams = [bagio.read_messages(b, self.wanted) for b in self.bags]
        return heapq.merge(*streams, key=lambda m: m.log_time_ns)


class Player:
    """Replays a BagSource into a FoxgloveBridge with recorded timing."""

    def __init__(self, source: BagSource, bridge, rate: float, stop: threading.Event, log=print):
        from maem_ros import wire  # message decoders only; no ROS graph

        self.source, self.bridge, self.rate, self.stop, self.log = source, bridge, rate, stop, log
        self.wire = wire
        self.sent = 0
        self.rejected: dict[str, int] = {}

    def play_once(self) -> None:
        t0_bag = t0_wall = None
        for m in self.source.messages():
            if self.stop.is_set():
                return
            if t0_bag is None:
                t0_bag, t0_wall = m.log_time_ns, time.monotonic()
            delay = t0_wall + (m.log_time_ns - t0_bag) / 1e9 / self.rate - time.monotonic()
            if delay > 0 and self.stop.wait(delay):
                return
            self.publish(m)

    def publish(self, m) -> None:
        """Decode one bag message and send it; a bad message is counted and logged (first of
        each kind), the replay goes on."""
        try:
            msg = m.decode()
            if m.topic == self.source.poses_topic:
                frame = self.wire.msg_to_poses(msg, m.topic)
                self.bridge.publish_poses(frame.stamp_ns, frame.ids, frame.joints, frame.frame_id)
            else:
                cam, kind = self.source.camera_of[m.topic]
                stamp = self.wire.checked_stamp_ns(msg.header.stamp, m.topic)
                if kind == "compressed":
                    self.bridge.publish_image(cam, stamp, bytes(msg.data), msg.format)
                elif kind == "raw":
                    self.bridge.publish_bgr(cam, stamp, self.wire.image_to_bgr(msg, m.topic))
                else:
                    self.bridge.publish_calibration(cam, stamp, camera_info_fields(msg))
            self.sent += 1
        except Exception as e:  # noqa: BLE001 - a bad message must not end the replay
            why = e if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"
            n = self.rejected.get(m.topic, 0)
            self.rejected[m.topic] = n + 1
            if n == 0:
                self.log(
                    f"skipped {m.topic} at log time {m.log_time_ns}: {why} (further skips "
                    f"on this topic are counted)"
                )


def run_bag(args: argparse.Namespace, log=print) -> int:
    """--bag mode: serve until the bag(s) ended (or Ctrl-C / SIGTERM with --loop)."""
    from maem_ros.viz.bridge import FoxgloveBridge

    if not args.rate > 0:
        raise InputError(f"--rate: {args.rate} must be > 0")
    if not 0 <= args.port <= 65535:
        raise InputError(f"--port: {args.port} is not a port number")
    if not all(v > 0 for v in args.court):
        raise InputError(f"--court: {args.court} must be positive")
    rig = load_rig(args)
    source = BagSource(args.bag, rig, args.topic, log)
    try:
        bridge = FoxgloveBridge(
            rig,
            host=args.host,
            port=args.port,
            court_size=tuple(args.court),
            convention=args.convention,
            world_frame=args.frame,
        )
    except OSError as e:
        raise InputError(f"--port {args.port}: {e}") from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    log(
        f"Foxglove server on {bridge.url} ({len(rig)} cameras, topics: {', '.join(source.wanted)})",
        flush=True,
    )
    player = Player(source, bridge, args.rate, stop, log)
    try:
        if not args.no_wait:
            log("waiting for a client to subscribe", flush=True)
            while not stop.is_set() and not bridge.wait_for_client(0.2):
                pass
        while not stop.is_set():
            player.play_once()
            if not args.loop:
                break
    finally:
        bridge.close()
    skipped = sum(player.rejected.values())
    log(f"sent {player.sent} messages" + (f", skipped {skipped}: {player.rejected}" if skipped else ""))
    return 0


def print_help() -> None:
    """The --bag options, then the live node's parameters (name, default, description)."""
    from maem_ros.ros.foxglove_node import PARAMS

    build_parser().print_help()
    print("\nlive node parameters (maem-foxglove --ros-args -p NAME:=VALUE):")
    for spec in PARAMS:
        print(f"  {spec.help_line()}")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--bag" not in argv and not any(a.startswith("--bag=") for a in argv):
        if "-h" in argv or "--help" in argv:
            print_help()
            return 0
        from maem_ros.ros.foxglove_node import main as node_main

        return node_main([sys.argv[0], *argv])
    args = build_parser().parse_args(argv)
    try:
        return run_bag(args, log=lambda *a, **k: print(*a, **{"flush": True, **k}))
    except InputError as e:
        return fail("maem-foxglove", e)


if __name__ == "__main__":
    sys.exit(main())
