"""Approximate-time synchroniser for per-camera messages (pure logic, injectable clock).

message_filters is not available from PyPI, so this is the project's own. Every call
passes ``now_ns`` (the caller's clock: wall or sim time), which keeps it testable.

Rules (DESIGN.md §5):

- Each camera has a short queue, kept sorted by stamp (at most ``queue_size``
  messages; when full the oldest is dropped, counted ``dropped_queue_full``).
- The reference is the oldest queued message. A camera is *present* when its
  oldest queued message lies within ``[ref, ref + slop]`` (it cannot be older than
  the reference). It is *known missing* when its oldest message is newer than
  ``ref + slop`` (stamps per camera only increase) or when it is *dead*: missing
  from the last ``dead_after_sets`` emitted sets without delivering anything since.
  A dead camera costs ``max_wait`` on a few sets, not on every frame. Silence is
  counted in sets, not seconds: a time rule would declare every camera dead whenever
  the frame period exceeds ``max_wait``, and a one-set rule would stop waiting for a
  camera that merely lags (its late messages keep it alive). A dead camera is picked
  up again with its next message, though if that first message arrives after the
  other cameras' messages of its frame, that frame is already out and the message
  counts as ``dropped_late``.
- A FrameSet is emitted, stamped with the reference stamp, as soon as every camera
  is present or known missing, or once ``max_wait`` has passed since the reference
  message arrived; if fewer than ``min_cameras`` are present then, only the
  reference message is dropped (``dropped_too_few_cameras``) and the next oldest
  becomes the reference. Emitted sets never go back in time: a message whose stamp
  is not newer than the last emitted reference is dropped (``dropped_late``).
- A stamp older than the same camera's previous one by more than ``slop`` (bag loop,
  restart) clears every queue first (``resets``); a smaller step back or a repeated
  stamp is dropped (``dropped_out_of_order``).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Sequence


@dataclass
class FrameSet:
    """Messages of one instant: items by camera name, missing cameras in rig order."""

    stamp_ns: int
    items: dict[str, Any]
    missing: list[str] = field(default_factory=list)


@dataclass
class _Msg:
    stamp_ns: int
    arrival_ns: int
    item: Any


_COUNTERS = ("received", "sets", "partial_sets", "dropped_late", "dropped_too_few_cameras",
             "dropped_out_of_order", "dropped_queue_full", "resets")


class ApproximateTimeSync:
    """Group per-camera messages whose stamps lie within ``slop_ns`` of a reference."""

    def __init__(self, cameras: Sequence[str], slop_ns: int, max_wait_ns: int,
                 min_cameras: int = 2, queue_size: int = 16, dead_after_sets: int = 3):
        cameras = list(cameras)
        if not cameras or len(set(cameras)) != len(cameras):
            raise ValueError(f"cameras: need a non-empty list of distinct names, got {cameras}")
        if int(slop_ns) < 0:
            raise ValueError(f"slop_ns: must be >= 0, got {slop_ns}")
        if int(max_wait_ns) < 0:
            raise ValueError(f"max_wait_ns: must be >= 0, got {max_wait_ns}")
        if not 1 <= int(min_cameras) <= len(cameras):
            raise ValueError(f"min_cameras: must be in 1..{len(cameras)}, got {min_cameras}")
        if int(queue_size) < 1:
            raise ValueError(f"queue_size: must be >= 1, got {queue_size}")
        if int(dead_after_sets) < 1:
            raise ValueError(f"dead_after_sets: must be >= 1, got {dead_after_sets}")
        self.dead_after_sets = int(dead_after_sets)
        self.cameras = cameras
        self.slop_ns = int(slop_ns)
        self.max_wait_ns = int(max_wait_ns)
        self.min_cameras = int(min_cameras)
        self.queue_size = int(queue_size)
        self.counters: dict[str, int] = dict.fromkeys(_COUNTERS, 0)
        self._queues: dict[str, deque[_Msg]] = {c: deque() for c in cameras}
        self.reset(count=False)

    def reset(self, count: bool = True) -> None:
        """Drop every queued message and forget all stamps."""
        for q in self._queues.values():
            q.clear()
        self._last_stamp: dict[str, int] = {}
        self._missed: dict[str, int] = {}  # sets missed in a row with nothing delivered since
        self._last_emitted: int | None = None
        if count:
            self.counters["resets"] += 1

    def pending(self) -> int:
        """Messages currently queued."""
        return sum(len(q) for q in self._queues.values())

    def add(self, camera: str, stamp_ns: int, item: Any, now_ns: int) -> list[FrameSet]:
        """Queue one message and return the frame sets that became complete."""
        if camera not in self._queues:
            raise ValueError(f"camera: unknown camera {camera!r}; expected one of {self.cameras}")
        stamp_ns, now_ns = int(stamp_ns), int(now_ns)
        self.counters["received"] += 1
        prev = self._last_stamp.get(camera)
        if prev is not None and stamp_ns <= prev:
            if prev - stamp_ns > self.slop_ns:
                self.reset()
            else:
                self.counters["dropped_out_of_order"] += 1
                return self.poll(now_ns)
        self._last_stamp[camera] = stamp_ns
        self._missed[camera] = 0
        if self._last_emitted is not None and stamp_ns <= self._last_emitted:
            self.counters["dropped_late"] += 1
            return self.poll(now_ns)
        q = self._queues[camera]
        if len(q) >= self.queue_size:
            q.popleft()
            self.counters["dropped_queue_full"] += 1
        q.append(_Msg(stamp_ns, now_ns, item))
        return self.poll(now_ns)

    def poll(self, now_ns: int) -> list[FrameSet]:
        """Emit every frame set that is complete or has waited long enough at ``now_ns``."""
        now_ns = int(now_ns)
        out: list[FrameSet] = []
        while True:
            heads = {c: q[0] for c, q in self._queues.items() if q}
            if not heads:
                return out
            ref_cam = min(heads, key=lambda c: heads[c].stamp_ns)
            ref = heads[ref_cam]
            limit = ref.stamp_ns + self.slop_ns
            present = [c for c in self.cameras if c in heads and heads[c].stamp_ns <= limit]
            decided = all(c in heads or self._dead(c) for c in self.cameras)
            if not decided and now_ns - ref.arrival_ns < self.max_wait_ns:
                return out
            if len(present) < self.min_cameras:
                self._queues[ref_cam].popleft()
                self.counters["dropped_too_few_cameras"] += 1
                continue
            out.append(self._emit(ref.stamp_ns, present))

    def _dead(self, camera: str) -> bool:
        return self._missed.get(camera, 0) >= self.dead_after_sets

    def _emit(self, stamp_ns: int, present: list[str]) -> FrameSet:
        items = {c: self._queues[c].popleft().item for c in present}
        missing = [c for c in self.cameras if c not in items]
        for c in missing:
            self._missed[c] = self._missed.get(c, 0) + 1
        self._last_emitted = stamp_ns
        self.counters["sets"] += 1
        if missing:
            self.counters["partial_sets"] += 1
        return FrameSet(stamp_ns, items, missing)
