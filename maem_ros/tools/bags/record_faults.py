"""maem-record-faults: crash, cut-file and full-disk runs against maem-record and the bag readers.

    maem-record-faults [--kills N] [--cuts N] [--disk] [--long MIN] [--seed S] [--work DIR]

Real processes, as a user runs them: ``maem-play BAG --loop --reliable-images`` feeds
``maem-record``, which is killed with SIGKILL at random moments (then ``maem-bag recover``), or
runs into a file size limit (RLIMIT_FSIZE: EFBIG) or a small tmpfs (ENOSPC, root only); a
finished bag is cut at random byte offsets. Every message read back must be byte-identical to one
the player published (nothing garbled), per topic in the player's order without a hole, and:

* kill: every message logged more than 1 s before the kill is there (newest >= kill - 1 s);
* cut: exactly the messages of the chunks that end before the cut are read back;
* full disk: the recorder exits non-zero with one line, the bag holds what the line says;
* long: a recording split every S s gives complete files and records every message received.

The numbers are printed as a table (doc/recording.md has one). The test suite
(test/test_recording_faults.py) runs a few of each; set ROS_DOMAIN_ID to keep runs apart.
"""

from __future__ import annotations

import functools
import random
import re
import resource
import shutil
import signal
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from maem_ros import bagio
from maem_ros.tools.processes import kill_with_stacks

BIN = Path(sys.executable).parent


def command(script: str, module: str) -> list[str]:
    """The console script next to this Python (as a user runs it), else ``python -m``."""
    exe = BIN / script
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", module]


PLAY = command("maem-play", "maem_ros.ros.player_node")
RECORD = command("maem-record", "maem_ros.ros.recorder_node")
BAG = command("maem-bag", "maem_ros.tools.bags.bag")


# ---------------------------------------------------------------------------------------------
# what the player publishes, and checks against it
# ---------------------------------------------------------------------------------------------
@dataclass
class Source:
    """Per topic the bag's messages in order (the player's order on every loop pass). The
    player publishes the bag's CDR bytes; Fast DDS delivers them zero-padded to a multiple of 4
    bytes, so a recorded message is identical to the bag's bytes or to those padded."""

    seqs: dict[str, list[bytes]]
    where: dict[str, dict[bytes, list[int]]]  # topic -> data -> positions in seqs[topic]

    @classmethod
    def load(cls, bag: Path) -> Source:
        seqs: dict[str, list[bytes]] = defaultdict(list)
        for m in bagio.read_messages(bag):
            seqs[m.topic].append(m.data)
        where: dict[str, dict[bytes, list[int]]] = {t: defaultdict(list) for t in seqs}
        for t, seq in seqs.items():
            for i, data in enumerate(seq):
                where[t][data].append(i)
                padded = data + bytes(-len(data) % 4)  # as DDS delivers it (4-byte multiple)
                if padded != data:
                    where[t][padded].append(i)
        return cls(dict(seqs), where)

    def check(self, msgs: Iterable[bagio.BagMessage], last: dict | None = None) -> Checked:
        """Stream ``msgs`` once: how many, how many are not byte-identical to one of the bag's
        on their topic (garbled), how many per-topic successions skip messages of the player's
        loop (holes), how many are on a topic the bag does not have (others: the recorder's
        own /diagnostics with --all), the newest log time. ``last`` carries the per-topic
        state across calls (files of one bag read one by one)."""
        last = {} if last is None else last
        out = Checked()
        for m in msgs:
            out.count += 1
            out.newest_ns = max(out.newest_ns, m.log_time_ns)
            if m.topic not in self.where:
                out.others += 1
                continue
            pos = self.where[m.topic].get(m.data)
            if pos is None:
                out.garbled += 1
                continue
            prev = last.get(m.topic)
            n = len(self.seqs[m.topic])
            if prev is not None and not any((i + 1) % n in pos for i in prev):
                out.holes += 1
            last[m.topic] = pos
        return out


@dataclass
class Checked:
    count: int = 0
    garbled: int = 0
    holes: int = 0
    others: int = 0
    newest_ns: int = 0


def run(cmd: list[str], timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)


class Feed:
    """``maem-play BAG --loop --reliable-images`` in the background (a context manager)."""

    def __init__(self, bag: Path, log: Path):
        self.bag, self.log = bag, log

    def __enter__(self) -> Feed:
        self.out = open(self.log, "w")
        self.proc = subprocess.Popen(
            [*PLAY, str(self.bag), "--loop", "--reliable-images", "--delay", "0.5"],
            stdout=self.out,
            stderr=subprocess.STDOUT,
        )
        return self

    def stop(self) -> str:
        """SIGINT, wait; the player's output."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.out.close()
        return self.log.read_text()

    def __exit__(self, *exc) -> None:
        self.stop()


def start_recorder(
    out: Path, args: Sequence[str], log: Path, preexec: Callable[[], None] | None = None
) -> subprocess.Popen:
    with open(log, "w") as f:
        return subprocess.Popen(
            [*RECORD, str(out), *args], stdout=f, stderr=subprocess.STDOUT, preexec_fn=preexec
        )


def wait_data(out: Path, proc: subprocess.Popen, min_bytes: int, timeout_s: float) -> bool:
    """Until the recording's files hold ``min_bytes`` (chunks on disk) or the recorder ended."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        if out.is_dir() and sum(p.stat().st_size for p in out.glob("*.mcap")) >= min_bytes:
            return True
        time.sleep(0.05)
    return False


# ---------------------------------------------------------------------------------------------
# SIGKILL
# ---------------------------------------------------------------------------------------------
@dataclass
class KillResult:
    delay_s: float
    topics: str
    window_s: float  # kill time - newest recovered log time
    recovered: int
    garbled: int
    holes: int
    cut_seen: bool  # maem-bag info said a file was cut (or lacked its summary)
    recover_rc: int
    recover_text: str
    restarts: int = 0  # recorders that received nothing in 30 s and were started again

    @property
    def ok(self) -> bool:
        """Recovered, nothing garbled, the newest message at most 1 s older than the kill.
        (Holes are messages DDS never delivered to the recorder, which writes every message
        it receives in order: reported apart, they depend on the machine's load.)"""
        return self.recover_rc == 0 and self.garbled == 0 and self.recovered > 0 and self.window_s <= 1.0


#: low-traffic runs record only small topics: their chunks are closed by time, not size
LOW_TRAFFIC = ["--topics", "/maem/gt_poses", "/camera_0/camera_info"]


def kill_run(
    out: Path, source: Source, rng: random.Random, low_traffic: bool, max_delay_s: float = 5.0
) -> KillResult:
    """Record from the running feed, SIGKILL after a random delay, ``maem-bag recover``."""
    args = LOW_TRAFFIC if low_traffic else ["--all"]
    for attempt in range(3):  # noqa: B007 - read after the loop; a recorder that never gets a message (DDS) is started again
        proc = start_recorder(out, args, out.with_suffix(".log"))
        if wait_data(out, proc, 4096 if low_traffic else 1 << 20, 30.0):
            break
        proc.kill()
        proc.wait(5)
        shutil.rmtree(out)
    else:
        raise RuntimeError(f"maem-record wrote nothing: {out.with_suffix('.log').read_text()}")
    try:
        delay = rng.uniform(0.2, max_delay_s)
        time.sleep(delay)
        kill_ns = time.time_ns()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    info = run([*BAG, "info", str(out)])
    rec = run([*BAG, "recover", str(out)])
    c = source.check(bagio.read_messages(out) if rec.returncode == 0 else [])
    return KillResult(
        delay,
        "low" if low_traffic else "all",
        (kill_ns - c.newest_ns) / 1e9,
        c.count,
        c.garbled,
        c.holes,
        "CUT SHORT" in info.stdout,
        rec.returncode,
        rec.stdout + rec.stderr,
        attempt,
    )


# ---------------------------------------------------------------------------------------------
# cut at a byte offset
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def chunk_contents(path: Path) -> list[tuple[int, list[tuple[str, int, bytes]]]]:
    """(end offset, messages) of every chunk of a complete MCAP file, from its chunk index
    (mcap library records), as the ground truth for cut files."""
    out = []
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        if summary is None:
            raise ValueError(
                f"MCAP file {str(path)!r}: no summary (not a complete file), its chunks cannot be listed"
            )
        topics = {cid: c.topic for cid, c in summary.channels.items()}
        for ci in summary.chunk_indexes:
            f.seek(ci.chunk_start_offset + 1 + 8)
            chunk = Chunk.read(ReadDataStream(f))
            msgs = [
                (topics[r.channel_id], r.log_time, bytes(r.data))
                for r in breakup_chunk(chunk)
                if isinstance(r, Message)
            ]
            out.append((ci.chunk_start_offset + ci.chunk_length, msgs))
    return out


@dataclass
class CutResult:
    offset: int
    size: int
    expected: int  # messages in chunks wholly before the cut
    got: int
    garbled: int  # read back but not in the file at all
    missing: int  # expected but not read back
    extra: int  # read back from a chunk that was cut
    refused: str  # the one-line error when nothing complete was left
    unordered: int = 0  # messages read back with a log time before the previous one's

    @property
    def ok(self) -> bool:
        return self.garbled == 0 and self.missing == 0 and self.extra == 0 and self.unordered == 0


def cut_run(bag: Path, work: Path, offset: int, drop_metadata: bool = False) -> CutResult:
    """Copy ``bag`` to ``work`` with its last file cut at ``offset`` bytes (and without
    metadata.yaml with ``drop_metadata``), read it back with bagio, compare with the chunks."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    files = bagio.bag_info(bag).files
    for fs in files[:-1]:
        shutil.copy(fs.path, work / fs.path.name)
    if not drop_metadata:
        shutil.copy(bag / "metadata.yaml", work / "metadata.yaml")
    last = files[-1].path
    with open(last, "rb") as f:
        (work / last.name).write_bytes(f.read(offset))
    truth = chunk_contents(last)
    earlier = [m for fs in files[:-1] for _, msgs in chunk_contents(fs.path) for m in msgs]
    expected = earlier + [m for end, msgs in truth if end <= offset for m in msgs]
    try:
        got = [(m.topic, m.log_time_ns, m.data) for m in bagio.read_messages(work)]
        refused = ""
    except bagio.BagError as e:
        got, refused = [], str(e)
    want, have = _multiset(expected), _multiset(got)
    known = {m for _, msgs in truth for m in msgs} | set(earlier)
    return CutResult(
        offset,
        last.stat().st_size,
        len(expected),
        len(got),
        sum(m not in known for m in got),
        sum(max(0, n - have.get(k, 0)) for k, n in want.items()),
        sum(max(0, n - want.get(k, 0)) for k, n in have.items()),
        refused,
        sum(b[1] < a[1] for a, b in zip(got, got[1:])),
    )


def _multiset(items) -> dict:
    out: dict = defaultdict(int)
    for it in items:
        out[it] += 1
    return out


# ---------------------------------------------------------------------------------------------
# full disk
# ---------------------------------------------------------------------------------------------
@dataclass
class DiskResult:
    mode: str  # "fsize" (RLIMIT_FSIZE: EFBIG) or "tmpfs" (ENOSPC)
    rc: int
    last_line: str
    said: int  # messages the recorder's line says are readable
    readable: int
    garbled: int
    holes: int
    damage: str
    #: attempts before this one whose recording stopped growing with the recorder still
    #: running: the end of each one's log, its Python stacks included (wait_exit_or_stall)
    stalls: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return (
            self.rc not in (0, None)
            and self.said == self.readable > 0
            and self.garbled == 0
            and "failed" in self.last_line
        )


def _said(line: str) -> int:
    """The message count in the recorder's full-disk line ('... stopped; 1,234 messages ...')."""
    try:
        return int(line.split("stopped; ", 1)[1].split(" messages", 1)[0].replace(",", ""))
    except (IndexError, ValueError):
        return -1


def limit_file_size(nbytes: int) -> Callable[[], None]:
    """preexec_fn: the child's files may not grow beyond ``nbytes`` (writes fail with EFBIG;
    Python ignores SIGXFSZ)."""

    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))

    return apply


def _recorded_bytes(out: Path) -> int:
    return sum(p.stat().st_size for p in out.glob("*.mcap")) if out.is_dir() else 0


def wait_exit_or_stall(proc: subprocess.Popen, out: Path, timeout_s: float, stall_s: float) -> int | None:
    """The recorder's exit code, or None when its files did not grow for ``stall_s`` (or in
    ``timeout_s``) while it ran: then it is sent SIGUSR1 (its Python stacks go to its log,
    ros/cli.stop_on_signals) and killed."""
    deadline = time.monotonic() + timeout_s
    size, grew = -1, time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - grew < stall_s:
        try:
            return proc.wait(0.2)
        except subprocess.TimeoutExpired:
            now = _recorded_bytes(out)
            if now != size:
                size, grew = now, time.monotonic()
    kill_with_stacks(proc)
    return None


def disk_full_run(
    out: Path, source: Source, mode: str, limit_mb: float, timeout_s: float = 90.0, stall_s: float = 15.0
) -> DiskResult:
    """Record from the running feed until the file size limit / the tmpfs at ``out.parent``
    (already mounted by the caller for tmpfs) is full.

    A recording that stops growing for ``stall_s`` while the recorder runs (seen once in a CI
    run: 59 messages, then nothing for 90 s, no line) is not a full-disk result: its log tail
    with the recorder's stacks is kept in ``stalls`` and the run starts again, three times at
    most (as kill_run does for a recorder that never gets a message)."""
    preexec = limit_file_size(int(limit_mb * bagio.writer.MB)) if mode == "fsize" else None
    log = out.parent.parent / f"{out.name}.{mode}.log"
    stalls: list[str] = []
    for _attempt in range(3):
        proc = start_recorder(out, ["--all"], log, preexec)
        rc = wait_exit_or_stall(proc, out, timeout_s, stall_s)
        if rc is not None:
            break
        stalls.append(log.read_text()[-4000:])
        shutil.rmtree(out, ignore_errors=True)
    else:
        rc = -9
    lines = [ln for ln in log.read_text().splitlines() if ln.startswith("maem-record:")]
    last = lines[-1] if lines else ""
    try:
        info = bagio.bag_info(out)
        c, damage = source.check(bagio.read_messages(out, info=info)), info.damage
    except bagio.BagError as e:
        c, damage = Checked(), str(e)
    return DiskResult(mode, rc, last, _said(last), c.count, c.garbled, c.holes, damage, tuple(stalls))


class Tmpfs:
    """A size-limited tmpfs mounted at ``path`` (root only); ``ok`` False with ``why``."""

    def __init__(self, path: Path, size_mb: float):
        self.path, self.size_mb, self.ok, self.why = path, size_mb, False, ""

    def __enter__(self) -> Tmpfs:
        self.path.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={int(self.size_mb)}m", "tmpfs", str(self.path)],
            capture_output=True,
            text=True,
        )
        self.ok = proc.returncode == 0
        self.why = " ".join((proc.stderr or proc.stdout).split()) or f"exit {proc.returncode}"
        return self

    def __exit__(self, *exc) -> None:
        if self.ok:
            subprocess.run(["umount", str(self.path)], capture_output=True)


# ---------------------------------------------------------------------------------------------
# a long split recording
# ---------------------------------------------------------------------------------------------
@dataclass
class LongResult:
    minutes: float
    split_s: float
    files: int
    complete: int
    written: int  # messages in the bag
    received: int  # messages the recorder says it received
    lost: int  # messages the recorder counted lost before it took them (sequence gaps)
    published: str  # the player's own count line
    holes: int
    garbled: int
    durations_s: list[float]

    @property
    def ok(self) -> bool:
        """Complete files and every received message written (holes are messages DDS did not
        deliver to the recorder: reported, a matter of the machine's load, not of the bag)."""
        return self.complete == self.files and self.written == self.received and self.garbled == 0


def _said_count(line: str, label: str) -> int:
    """The number after ``label`` in the recorder's last line (-1 when it is not there)."""
    m = re.search(re.escape(label) + r"([\d,]+)", line)
    return int(m.group(1).replace(",", "")) if m else -1


def long_run(out: Path, source: Source, feed: Feed, minutes: float, split_s: float) -> LongResult:
    """Record everything for ``minutes`` split every ``split_s``, stop with SIGINT."""
    log = out.with_suffix(".log")
    proc = start_recorder(out, ["--all", "--max-bag-duration", str(split_s)], log)
    time.sleep(minutes * 60)
    proc.send_signal(signal.SIGINT)
    proc.wait(120)
    published = [ln for ln in feed.stop().splitlines() if "published" in ln]
    text = log.read_text()
    line = [ln for ln in text.splitlines() if "wrote" in ln and "received" in ln]
    received, lost = (
        (_said_count(line[-1], "received "), _said_count(line[-1], "took them: ")) if line else (-1, -1)
    )
    info = bagio.bag_info(out)
    c = source.check(bagio.read_messages(out, info=info))
    return LongResult(
        minutes,
        split_s,
        len(info.files),
        sum(fs.complete for fs in info.files),
        info.message_count,
        received,
        lost,
        published[-1] if published else "",
        c.holes,
        c.garbled,
        [((fs.end_ns or 0) - (fs.start_ns or 0)) / 1e9 for fs in info.files],
    )


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def _default_bag() -> Path:
    """bags/demo of the source checkout (demo_bag.default_bag without importing the
    simulator)."""
    return Path(__file__).resolve().parents[3] / "bags" / "demo"


def cut_bag(bag: Path, work: Path) -> Path:
    """The player's bag rewritten by BagWriter (0.5 s / 1 MB chunks, as maem-record writes)."""
    out = work / "cut_src"
    info = bagio.bag_info(bag)
    with bagio.BagWriter(out, durable=False) as w:
        for k, v in info.custom.items():
            w.set_custom(k, v)
        for m in bagio.read_messages(bag, info=info):
            qos = info.qos.get(m.topic)
            w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, qos[0] if qos else None)
    return out
