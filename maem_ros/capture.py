"""Camera capture without ROS: frame sources (device, video file, stream URL, image folder) and
the open / read / reconnect state machine the camera node drives from its timer.

Times: ``Capture.poll(now)`` takes monotonic seconds; sources stamp frames with the clock
function they are given (integer ns, taken right after the grab).
"""

from __future__ import annotations

import glob as globmod
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")


# ---------------------------------------------------------------------------------------------
# frame sources
# ---------------------------------------------------------------------------------------------
class FrameSource(Protocol):
    """One openable image source. ``finite``: its end is normal (file/folder), not a failure."""

    description: str
    finite: bool

    def open(self) -> bool: ...

    def read(self) -> tuple[np.ndarray | None, int]:
        """(frame or None at end/failure, stamp ns taken right after the grab)."""

    def rewind(self) -> bool: ...

    def release(self) -> None: ...


def _natural_key(s: str):
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", s)]


class ImageFolderSource:
    """Images of a folder (known extensions) or a glob pattern, in natural order."""

    finite = True

    def __init__(self, pattern: str, clock_ns: Callable[[], int]):
        self.pattern = pattern
        self.description = f"image folder {pattern!r}"
        self._clock_ns = clock_ns
        self._files: list[str] = []
        self._index = 0

    def _list(self) -> list[str]:
        p = Path(self.pattern).expanduser()
        if p.is_dir():
            files = [str(f) for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS]
        else:
            files = [f for f in globmod.glob(str(p)) if os.path.isfile(f)]
        return sorted(files, key=_natural_key)

    def open(self) -> bool:
        self._files = self._list()
        self._index = 0
        return bool(self._files)

    def read(self) -> tuple[np.ndarray | None, int]:
        if self._index >= len(self._files):
            return None, 0
        path = self._files[self._index]
        self._index += 1
        stamp = self._clock_ns()
        frame = cv2.imread(path, cv2.IMREAD_COLOR)
        if frame is None:
            raise UnreadableFrame(f"unreadable image {path!r}, skipped")
        return frame, stamp

    def rewind(self) -> bool:
        self._index = 0
        return bool(self._files)

    def release(self) -> None:
        self._index = len(self._files)


class VideoSource:
    """cv2.VideoCapture on a device index, a video file or a stream URL."""

    def __init__(self, spec: str | int, clock_ns: Callable[[], int], open_timeout_s: float = 5.0):
        self.spec = spec
        self.finite = isinstance(spec, str) and "://" not in spec  # a local file ends; streams fail
        kind = "device" if isinstance(spec, int) else ("video file" if self.finite else "stream")
        self.description = f"{kind} {spec!r}"
        self._clock_ns = clock_ns
        self._timeout_ms = int(1000 * open_timeout_s)
        self._cap: cv2.VideoCapture | None = None

    def open(self) -> bool:
        self.release()
        if isinstance(self.spec, int):
            cap = cv2.VideoCapture(self.spec)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # newest frame, not a queued one (V4L2)
        else:
            target = str(Path(self.spec).expanduser()) if self.finite else self.spec
            cap = cv2.VideoCapture(
                target,
                cv2.CAP_ANY,
                [
                    cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                    self._timeout_ms,
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                    self._timeout_ms,
                ],
            )
        if not cap.isOpened():
            cap.release()
            return False
        self._cap = cap
        return True

    def read(self) -> tuple[np.ndarray | None, int]:
        if self._cap is None or not self._cap.grab():
            return None, 0
        stamp = self._clock_ns()
        ok, frame = self._cap.retrieve()
        return (frame if ok and frame is not None else None), stamp

    def rewind(self) -> bool:
        return self.open()

    def release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def make_source(spec: str, clock_ns: Callable[[], int], open_timeout_s: float = 5.0) -> FrameSource:
    """The FrameSource for a ``source`` parameter value (see the module docstring)."""
    spec = spec.strip()
    if not spec:
        raise ValueError("empty; give a device index, video file, stream URL or image folder/glob")
    if re.fullmatch(r"\d+", spec):
        return VideoSource(int(spec), clock_ns, open_timeout_s)
    p = Path(spec).expanduser()
    if p.is_dir() or (not p.exists() and any(c in spec for c in "*?[") and "://" not in spec):
        return ImageFolderSource(spec, clock_ns)
    return VideoSource(spec, clock_ns, open_timeout_s)


# ---------------------------------------------------------------------------------------------
# open / read / reconnect state machine (clock passed in)
# ---------------------------------------------------------------------------------------------
class UnreadableFrame(OSError):
    """One bad frame of a source that is otherwise fine (e.g. a corrupt file in a folder):
    skipped and counted, the source is not reopened."""


@dataclass
class Poll:
    """Result of one capture tick: a frame, or status 'skipped' | 'waiting' | 'ended' | 'failed'."""

    status: str
    frame: np.ndarray | None = None
    stamp_ns: int = 0
    message: str = ""


@dataclass
class CaptureCounters:
    opens: int = 0
    open_failures: int = 0
    reconnects: int = 0
    read_failures: int = 0
    skipped: int = 0
    loops: int = 0
    frames: int = 0


@dataclass
class Capture:
    """Opens ``source``, reads frames, reopens after failures with exponential backoff.

    Delays (s): after the k-th consecutive failed attempt the next one waits
    ``min(backoff * 2**(k-1), backoff_max)``. A source never opened fails for good after
    ``open_attempts`` failed attempts; one that was open retries forever unless
    ``max_reconnects`` > 0 consecutive reopen attempts failed.
    """

    source: FrameSource
    loop: bool = False
    open_attempts: int = 5
    backoff: float = 0.5
    backoff_max: float = 10.0
    max_reconnects: int = 0
    counters: CaptureCounters = field(default_factory=CaptureCounters)

    def __post_init__(self) -> None:
        self._open = False
        self._ever_opened = False
        self._failed_attempts = 0
        self._next_attempt = -float("inf")
        self._final: Poll | None = None

    @property
    def is_open(self) -> bool:
        return self._open

    def delay(self, failed_attempts: int) -> float:
        """s to wait after ``failed_attempts`` consecutive failures (>= 1)."""
        return min(self.backoff * 2.0 ** (failed_attempts - 1), self.backoff_max)

    def poll(self, now: float) -> Poll:
        """One tick at monotonic time ``now`` (s)."""
        if self._final is not None:
            return self._final
        if not self._open:
            result = self._try_open(now)
            if result is not None:
                return result
        try:
            frame, stamp = self.source.read()
            if frame is None and self.source.finite:
                if not self.loop:
                    return self._finish(Poll("ended", message=f"end of {self.source.description}"))
                self.counters.loops += 1
                if not self.source.rewind():
                    return self._lost(now, "cannot restart at its end")
                frame, stamp = self.source.read()
        except UnreadableFrame as e:
            self.counters.skipped += 1
            return Poll("skipped", message=str(e))
        except OSError as e:
            return self._lost(now, str(e))
        if frame is None:
            return self._lost(now, "read failed")
        self.counters.frames += 1
        return Poll("frame", frame, stamp)

    def _try_open(self, now: float) -> Poll | None:
        if now < self._next_attempt:
            return Poll("waiting")
        if self.source.open():
            self._open = True
            self.counters.opens += 1
            if self._ever_opened:
                self.counters.reconnects += 1
            self._ever_opened = True
            self._failed_attempts = 0
            return None
        self.counters.open_failures += 1
        self._failed_attempts += 1
        if not self._ever_opened and self._failed_attempts >= self.open_attempts:
            return self._finish(
                Poll(
                    "failed",
                    message=(
                        f"cannot open {self.source.description} after {self._failed_attempts} attempts; "
                        "check the path/URL/device index and that nothing else holds the device"
                    ),
                )
            )
        if self._ever_opened and 0 < self.max_reconnects <= self._failed_attempts:
            return self._finish(
                Poll(
                    "failed",
                    message=(
                        f"lost {self.source.description}; {self._failed_attempts} reopen attempts failed"
                    ),
                )
            )
        self._next_attempt = now + self.delay(self._failed_attempts)
        return Poll(
            "waiting",
            message=f"cannot open {self.source.description}, retrying in "
            f"{self.delay(self._failed_attempts):.1f} s",
        )

    def _lost(self, now: float, why: str) -> Poll:
        self.counters.read_failures += 1
        self.source.release()
        self._open = False
        self._next_attempt = now  # first reopen immediately, then back off
        return Poll("waiting", message=f"{self.source.description}: {why}; reconnecting")

    def _finish(self, result: Poll) -> Poll:
        self.source.release()
        self._open = False
        self._final = result
        return result

    def close(self) -> None:
        self.source.release()
        self._open = False


# ---------------------------------------------------------------------------------------------
# pixels
# ---------------------------------------------------------------------------------------------
def to_bgr(frame: np.ndarray) -> np.ndarray:
    """Any uint8 mono / BGR / BGRA capture -> BGR uint8 (H,W,3)."""
    if frame.dtype != np.uint8:
        raise ValueError(f"image: expected uint8 pixels, got {frame.dtype}")
    if frame.ndim == 2 or frame.shape[2] == 1:
        return cv2.cvtColor(frame.reshape(frame.shape[:2]), cv2.COLOR_GRAY2BGR)
    return cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR) if frame.shape[2] == 4 else frame
