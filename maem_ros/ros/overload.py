"""The overload policy (core.backlog) in a node: /diagnostics of the backlog, counted skips.

/diagnostics keys (strings, times in s on the node clock unless named ms):
``backlog/policy`` (``skip stale`` or ``keep every set``), ``backlog/bound_ms`` (frames that
waited longer are skipped; ``nan`` with keep_every_set), ``backlog/last_ms`` (the oldest frame's
wait for the node at the last decision), ``backlog/max_ms`` (the largest such wait over the
last period), ``behind`` (``true`` while the node skips frames or works on frames older than
the bound), ``behind/for_s`` (the current episode so far, 0 when not behind),
``behind/episodes`` (ended episodes), ``behind/total_s``, ``behind/longest_s``. While behind
the status is WARN with "behind for X s". Skipped frames are counted ``dropped/behind``.
"""

from __future__ import annotations

from collections.abc import Mapping

from rclpy.node import Node

from maem_ros.core.backlog import BACKLOG_PERIODS, MIN_BACKLOG_S, Backlog, BacklogParams
from maem_ros.ros.diagnostics import Diagnostics

#: the /diagnostics reason of a frame skipped by the overload policy
BEHIND = "behind"


class NodeBacklog:
    """A node's Backlog, its skips counted in ``diag`` and its state in every /diagnostics."""

    def __init__(self, node: Node, diag: Diagnostics, params: BacklogParams, what: str):
        self.policy: Backlog = Backlog(params)
        self._node, self._diag, self._what = node, diag, what
        self._catching_up = False  # a stale frame of this batch was skipped (still_fresh)
        diag.add_source(self.diagnostics)
        kind = (
            "keeps every frame (keep_every_set: true)"
            if params.keep_every_set
            else f"skips {what} that waited longer than "
            + (
                f"{params.max_backlog:g} s"
                if params.max_backlog > 0
                else f"{BACKLOG_PERIODS:g} frame periods (at least {MIN_BACKLOG_S:g} s)"
            )
            + " for the node (counted dropped/behind)"
        )
        node.get_logger().info(f"overload policy: {kind}")

    def now_ns(self) -> int:
        return self._node.get_clock().now().nanoseconds

    def count_skipped(self, n: int, newest_stamp_ns: int) -> None:
        """Count ``n`` skipped frames (``dropped/behind``) with one throttled log line."""
        if n <= 0:
            return
        bound = self.policy.bound_ns() or 0
        self._diag.reject(
            BEHIND,
            f"{n} {self._what} that waited more than {bound / 1e6:.0f} ms "
            f"for this node skipped (it fell behind the input rate); the newest "
            f"is stamped {newest_stamp_ns}",
            n=n,
        )

    def select(self, frames: list, ready_ns: list[int], stamps: list[int]) -> list:
        """The frames to process of those waiting together (in stamp order); the others are
        counted skipped."""
        for s in stamps:
            self.policy.observe(s)
        kept, skipped = self.policy.select(frames, ready_ns, self.now_ns())
        if skipped:
            self.count_skipped(len(skipped), stamps[-1])
        return kept

    def still_fresh(self, ready_ns: int, stamp_ns: int, newer_waiting: bool) -> bool:
        """Before processing a kept frame: False (counted skipped) when it has gone stale while
        the frames ahead of it were processed and a newer one waits; with ``catch_up: newest``
        the frames after it are skipped too, up to the newest."""
        if not newer_waiting:
            self._catching_up = False
            return True
        now = self.now_ns()
        if self._catching_up or self.policy.is_stale(ready_ns, now):
            self._catching_up = self.policy.params.catch_up == "newest"
            self.policy.skip(now)
            self.count_skipped(1, stamp_ns)
            return False
        return True

    def diagnostics(self) -> tuple[Mapping[str, str], str | None]:
        """The /diagnostics values and, while behind, the warning (Diagnostics.add_source)."""
        st = self.policy.status(self.now_ns())
        values = {
            "backlog/policy": "keep every set" if self.policy.params.keep_every_set else "skip stale",
            "backlog/bound_ms": f"{st.bound_s * 1e3:.1f}",
            "backlog/last_ms": f"{st.last_backlog_s * 1e3:.1f}",
            "backlog/max_ms": f"{st.max_backlog_s * 1e3:.1f}",
            "behind": "true" if st.behind else "false",
            "behind/for_s": f"{st.behind_for_s:.3f}",
            "behind/episodes": str(st.episodes),
            "behind/total_s": f"{st.behind_total_s:.3f}",
            "behind/longest_s": f"{st.longest_s:.3f}",
        }
        warning = (
            (f"behind for {st.behind_for_s:.1f} s (backlog up to {st.max_backlog_s * 1e3:.0f} ms)")
            if st.behind
            else None
        )
        return values, warning
