"""Taking messages: counted subscriptions (inputs and DDS losses in /diagnostics), taking every
pending sample now, and when a message reached the process."""

from __future__ import annotations

import inspect
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import QoSProfile

from maem_ros.ros.diagnostics import Diagnostics
from maem_ros.ros.raw_take import ARRAY_TAKE, take_message


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


def subscribe_counted(
    node: Node,
    diag: Diagnostics,
    msg_type: Any,
    topic: str,
    callback: Callable[..., None],
    qos: QoSProfile,
    raw: bool = False,
    with_info: bool = False,
    lost_reason: str = "dds_lost",
    into_array: bool = False,
):
    """create_subscription whose callback first records the input in ``diag`` and counts
    messages lost before the node took them (``dropped/<lost_reason>``, default
    ``dropped/dds_lost``; see SequenceGaps).

    ``raw``: the callback gets the serialized message (bytes), for decoders that read it in
    place (wire.cdr_to_cloud); ``with_info``: it gets ``(msg, info)``, the rmw message info
    (``received_timestamp`` etc., see :func:`arrival_ns`); ``into_array`` (with ``raw``): the
    serialized message comes as a uint8 array its decoded views may keep, taken without
    rclpy's extra copy (ros.raw_take; by :func:`take_pending` and the ArrayTakeExecutor)."""
    gaps = SequenceGaps()
    sub = None

    def on_message(*taken: Any) -> None:
        # SingleThreadedExecutor and take_pending call (msg, info); rclpy's EventsExecutor
        # (Jazzy 7.1) passes the (msg, info) tuple as one argument
        msg, info = taken if len(taken) == 2 else taken[0]
        diag.input(topic)
        lost = gaps.lost(info, sub.get_publisher_count)  # type: ignore[attr-defined]  # set below
        if lost:
            diag.reject(
                lost_reason,
                f"{topic}: {lost} message(s) overwritten in the DDS history "
                f"before this node took them (node too slow for the input rate)",
                n=lost,
            )
        if with_info:
            callback(msg, info)
        else:
            callback(msg)

    # rclpy: a callback that wants the info
    # (mypy: functions have no __signature__ attribute; inspect reads it)
    on_message.__signature__ = _MSG_INFO_SIGNATURE  # type: ignore[attr-defined]
    sub = node.create_subscription(msg_type, topic, on_message, qos, raw=raw)
    if raw and into_array:
        setattr(sub, ARRAY_TAKE, True)
    return sub


_MSG_INFO_SIGNATURE = inspect.Signature(
    [inspect.Parameter(name, inspect.Parameter.POSITIONAL_ONLY) for name in ("msg", "info")]
)


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
                got = take_message(sub)
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


class QueuedArrival:
    """When a message would have reached this process had nothing queued it on its way: the
    earlier of :func:`arrival_ns` and now minus its *excess transit*, per topic.

    Transit is the time from the writer's ``source_timestamp`` to now (system clock, ns). Its
    minimum over the last WINDOW_NS is the topic's baseline: the network's or the transport's
    latency and any offset between the machines' clocks, which are not the node falling
    behind. What a message took beyond that waited in a queue: the DDS reader history (what
    :func:`arrival_ns` alone sees), but also the shared-memory port or the receive thread of a
    process short of CPU, where full-mesh messages at 60 fps queue before the rmw stamps them
    received. A node's backlog bound (core.backlog) counts from this time, so it sees every
    queue on the way and not only the last one."""

    #: baseline window (ns): long enough that a backlog of several seconds does not become
    #: the baseline, short enough to follow a changed route or clock
    WINDOW_NS = 10 * 10**9

    def __init__(self) -> None:
        # per topic: (wall ns, transit ns) with increasing transit, oldest first (sliding min)
        self._mins: dict[str, deque[tuple[int, int]]] = {}

    def arrival_ns(self, topic: str, now_ns: int, info: Mapping[str, Any] | None) -> int:
        """The message's effective arrival on the caller's clock (``now_ns``)."""
        received = arrival_ns(now_ns, info)
        source = (info or {}).get("source_timestamp")
        if not isinstance(source, int) or source <= 0:
            return received
        wall = time.time_ns()
        transit = wall - source
        mins = self._mins.setdefault(topic, deque())
        while mins and mins[-1][1] >= transit:
            mins.pop()
        mins.append((wall, transit))
        while mins[0][0] < wall - self.WINDOW_NS:
            mins.popleft()
        excess = max(0, transit - mins[0][1])
        return min(received, int(now_ns) - excess)
