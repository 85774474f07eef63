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
from collections import deque
from typing import Sequence

import numpy as np

#: tracks whose history is kept (the least recently seen are forgotten first)
_MAX_TRACKS = 1000
#: limb bones checked, (proximal, distal) joint names
LIMB_BONES = (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle"))


def limb_bones(names: Sequence[str]) -> np.ndarray:
    """(B,2) (proximal, distal) joint indices of the limb bones present in a convention."""
    idx = {n: i for i, n in enumerate(names)}
    return np.array([(idx[f"{s}_{a}"], idx[f"{s}_{b}"]) for s in ("left", "right")
                     for a, b in LIMB_BONES if f"{s}_{a}" in idx and f"{s}_{b}" in idx],
                    dtype=np.int64).reshape(-1, 2)


class BoneLengthFilter:
    """Per track id, recent bone lengths; marks implausible distal joints NaN (module doc)."""

    def __init__(self, names: Sequence[str], tolerance: float, history: int = 60,
                 min_samples: int = 5):
        if not np.isfinite(tolerance) or tolerance <= 0:
            raise ValueError(f"bone_tolerance: must be > 0 (a fraction of the bone length), "
                             f"got {tolerance}")
        self.bones = limb_bones(names)
        self.tolerance = float(tolerance)
        self.history = int(history)
        self.min_samples = int(min_samples)
        self._lengths: dict[int, deque] = {}

    def reset(self) -> None:
        self._lengths.clear()

    def apply(self, ids: np.ndarray, joints: np.ndarray) -> int:
        """Mark implausible distal joints of ``joints`` (P,J,3 world m) NaN in place; returns
        how many joints were marked."""
        if not len(self.bones) or not len(ids):
            return 0
        prox, dist = self.bones[:, 0], self.bones[:, 1]
        # a bone hanging from a joint another bone marks is not checked: its length would be
        # measured from a wrong joint
        child_of = (prox[:, None] == dist[None, :])  # (B,B) bone b starts where bone c ends
        marked = 0
        for p, pid in enumerate(np.asarray(ids).tolist()):  # per person: each has its history
            if pid < 0:
                continue
            past = self._lengths.pop(pid, None) or deque(maxlen=self.history)
            self._lengths[pid] = past  # most recently seen last (bounded below)
            length = np.linalg.norm(joints[p, dist] - joints[p, prox], axis=-1)  # (B,)
            if len(past) >= self.min_samples:
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # a bone never measured
                    ref = np.nanmedian(np.stack(past), axis=0)
                bad = np.abs(length - ref) > self.tolerance * ref  # False where NaN
                bad &= ~(child_of & bad[None, :]).any(1)
                joints[p, dist[bad]] = np.nan
                marked += int(bad.sum())
            past.append(length)
        while len(self._lengths) > _MAX_TRACKS:  # ids are never reused: forget the oldest
            del self._lengths[next(iter(self._lengths))]
        return marked
