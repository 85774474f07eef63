"""Bone-length plausibility on a track (beyond the paper; off by default).

A person's bones keep their length. With ``bone_tolerance`` t > 0, each limb bone (upper arm,
forearm, thigh, shin) of a tracked person is compared with the median of that bone's lengths over
the track's last ``history`` frames; when the new length differs from that median by more than
t x median, the bone's distal joint (elbow, wrist, knee, ankle) is published as NaN (missing):
a joint triangulated from two views that agree with each other but not with the body, e.g. two
hallucinated wrists of an arm behind the body. Nothing is moved or smoothed: a joint is kept as
triangulated or marked missing. The median uses every measured length (accepted or not), so
the first frames cannot lock a wrong length in; it is applied once a track has ``min_samples``
lengths of the bone. Untracked people (id < 0) pass unchanged.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

#: tracks whose history is kept (the least recently seen are forgotten first)
_MAX_TRACKS = 1000
#: limb bones checked, (proximal, distal) joint names
LIMB_BONES = (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle"))


def limb_bones(names: Sequence[str]) -> np.ndarray:
    """(B,2) (proximal, distal) joint indices of the limb bones present in a convention."""
    idx = {n: i for i, n in enumerate(names)}
    return np.array(
        [
            (idx[f"{s}_{a}"], idx[f"{s}_{b}"])
            for s in ("left", "right")
            for a, b in LIMB_BONES
            if f"{s}_{a}" in idx and f"{s}_{b}" in idx
        ],
        dtype=np.int64,
    ).reshape(-1, 2)


class BoneLengthFilter:
    """Per track id, recent bone lengths; marks implausible distal joints NaN (module doc).

    The histories live in one array (rows, history, B) m, NaN where not (yet) measured, one
    row per live track: a frame's medians are one nanmedian over all its tracked people (the
    NaN padding of a short history is ignored like an unmeasured length).
    """

    def __init__(self, names: Sequence[str], tolerance: float, history: int = 60, min_samples: int = 5):
        if not np.isfinite(tolerance) or tolerance <= 0:
            raise ValueError(f"bone_tolerance: must be > 0 (a fraction of the bone length), got {tolerance}")
        self.bones = limb_bones(names)
        self.tolerance = float(tolerance)
        self.history = int(history)
        self.min_samples = int(min_samples)
        prox, dist = self.bones[:, 0], self.bones[:, 1]
        # a bone hanging from a joint another bone marks is not checked: its length would be
        # measured from a wrong joint
        self._child_of = prox[:, None] == dist[None, :]  # (B,B) bone b starts where bone c ends
        self.reset()

    def reset(self) -> None:
        self._rows: dict[int, int] = {}  # track id -> row, least recently seen first
        self._lengths = np.full((0, self.history, len(self.bones)), np.nan)
        self._count = np.zeros(0, np.int64)  # lengths appended per row (ring buffer position)
        self._free: list[int] = []

    def apply(self, ids: np.ndarray, joints: np.ndarray) -> int:
        """Mark implausible distal joints of ``joints`` (P,J,3 world m) NaN in place; returns
        how many joints were marked."""
        ids = np.asarray(ids).reshape(-1)
        if not len(self.bones) or not len(ids):
            return 0
        people = np.flatnonzero(ids >= 0)  # untracked people pass unchanged
        rows = np.array([self._row(int(pid)) for pid in ids[people]], np.int64)
        prox, dist = self.bones[:, 0], self.bones[:, 1]
        length = np.linalg.norm(joints[people][:, dist] - joints[people][:, prox], axis=-1)
        marked = 0
        # a track id twice in one frame sees its own first length: its occurrences in turn
        occurrence = np.zeros(len(rows), np.int64)
        if len(np.unique(rows)) < len(rows):
            for k in range(1, len(rows)):
                occurrence[k] = np.count_nonzero(rows[:k] == rows[k])
        for k in range(int(occurrence.max(initial=-1)) + 1):
            now = np.flatnonzero(occurrence == k)
            marked += self._check(people[now], rows[now], length[now], joints)
            self._append(rows[now], length[now])
        while len(self._rows) > _MAX_TRACKS:  # ids are never reused: forget the oldest
            self._release(self._rows.pop(next(iter(self._rows))))
        return marked

    def _row(self, pid: int) -> int:
        """The history row of track ``pid``, now the most recently seen (a new row if new)."""
        row = self._rows.pop(pid, None)
        if row is None:
            if not self._free:
                grow = max(len(self._count), 8)
                self._lengths = np.concatenate(
                    [self._lengths, np.full((grow,) + self._lengths.shape[1:], np.nan)]
                )
                self._count = np.concatenate([self._count, np.zeros(grow, np.int64)])
                self._free = list(range(len(self._count) - 1, len(self._count) - grow - 1, -1))
            row = self._free.pop()
        self._rows[pid] = row
        return row

    def _release(self, row: int) -> None:
        self._lengths[row] = np.nan
        self._count[row] = 0
        self._free.append(row)

    def _check(self, people: np.ndarray, rows: np.ndarray, length: np.ndarray, joints: np.ndarray) -> int:
        """Mark the distal joints of bones off their track's median (tracks with min_samples
        lengths); people, rows (K,) distinct tracks; length (K,B) m."""
        judged = np.minimum(self._count[rows], self.history) >= self.min_samples
        if not judged.any():
            return 0
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a bone never measured
            ref = np.nanmedian(self._lengths[rows[judged]], axis=1)  # (K',B)
        bad = np.abs(length[judged] - ref) > self.tolerance * ref  # False where NaN
        bad &= ~(self._child_of[None] & bad[:, None, :]).any(-1)
        who, bone = np.nonzero(bad)
        joints[people[judged][who], self.bones[bone, 1]] = np.nan
        return int(bad.sum())

    def _append(self, rows: np.ndarray, length: np.ndarray) -> None:
        """Append (K,B) lengths to distinct rows (ring buffers: the last ``history`` kept)."""
        self._lengths[rows, self._count[rows] % self.history] = length
        self._count[rows] += 1
