"""Writing rosbag2 MCAP bags that survive crashes: bounded chunks, a current metadata.yaml,
rosbag2-style splitting, a clean stop on a full disk.

The MCAP files are written with the ``mcap`` library's Writer (schemas, channels and QoS as
rosbag2 stores them, so rosbags, ``ros2 bag`` and Foxglove read them); metadata.yaml is this
package's own (bagio.metadata). What a crash can cost:

* messages wait in memory in the open chunk until it holds ``chunk_size`` MB or spans
  ``chunk_duration`` s of log time (checked on every write; ``tick()`` also writes it once its
  first message waited that long on the wall clock); a whole chunk is then written with one
  write() and flushed to the OS, and fsync'ed at most every ``chunk_duration`` s on a
  background thread (a slow disk never stalls the writing thread), so a killed process or a
  power cut loses about ``chunk_duration``. Offline writers (no tick) get chunks that depend on
  the messages only, so their files are reproducible byte for byte;
* metadata.yaml is written when the bag opens, on every split and every ``metadata_period``
  s (atomically), listing only what is on disk;
* a write error (ENOSPC, EFBIG from a file size limit, EIO) cuts the file back to its last whole
  chunk, writes metadata.yaml if it can and raises BagWriteError saying what was kept.
"""

from __future__ import annotations

import datetime
import errno
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, cast

import mcap
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import dump_qos_v8

from maem_ros.bagio import metadata
from maem_ros.bagio.messages import (
    QOS_RELIABLE,
    QOS_SENSOR,
    is_image_type,
    known_type,
    msgtype_of,
    schema_text,
    serialize,
)
from maem_ros.core.paramspec import Params, param

MB = 1_000_000


@dataclass
class WriteOptions(Params):
    """How a bag is written: the recorder's parameters (one definition: maem-record's flags
    ``--max-bag-duration`` etc. and its ROS parameters ``max_bag_duration`` etc. come from
    these fields)."""

    max_bag_duration: float = param(
        0.0, "s, start a new file when the open one spans this much log time (0 = one file)", minimum=0.0
    )
    max_bag_size: float = param(
        0.0, "MB, start a new file when the open one reaches this size (0 = one file)", minimum=0.0
    )
    chunk_duration: float = param(
        0.5,
        "s, longest a message waits in memory before its chunk is written (what a crash can lose)",
        minimum=0.0,
        exclusive_minimum=True,
    )
    chunk_size: float = param(
        1.0, "MB, uncompressed size at which a chunk is written", minimum=0.0, exclusive_minimum=True
    )
    compress: bool = param(False, "zstd compression of MCAP chunks")
    metadata_period: float = param(
        2.0, "s, longest time between metadata.yaml rewrites", minimum=0.0, exclusive_minimum=True
    )


def _utc(stamp_ns: int) -> str:
    """Log time as UTC, e.g. '2026-12-04 17:03:12.345 UTC'."""
    t = datetime.datetime.fromtimestamp(stamp_ns / 1e9, tz=datetime.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


class BagWriteError(OSError):
    """Writing stopped (a full disk, a file size limit, an I/O error): one line saying which
    file, why and what the bag holds."""


class _Unbuffered:
    """The file stream given to the mcap Writer: every write goes straight to the OS (a
    crash never leaves a half record in a Python buffer), tell() is the file offset."""

    def __init__(self, path: Path):
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self.offset = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            self.offset += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.offset

    def flush(self) -> None:
        """Nothing is buffered here."""

    def close(self) -> None:
        os.close(self.fd)


class _Syncer:
    """fsync on a background thread (os.fsync releases the GIL): ``request(fd)`` asks for a
    sync of the open file, ``forget()`` returns once no sync runs and none will run on the
    descriptor given before (call it before closing the file). An fsync error is kept in
    ``error`` for the writer to raise."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # held while fsync runs
        self._wake = threading.Event()
        self._fd: int | None = None
        self._stopped = False
        self.error: OSError | None = None
        self._thread = threading.Thread(target=self._run, name="bag-fsync", daemon=True)
        self._thread.start()

    def request(self, fd: int) -> None:
        self._fd = fd
        self._wake.set()

    def forget(self) -> None:
        with self._lock:
            self._fd = None

    def stop(self) -> None:
        self._stopped = True
        self.forget()
        self._wake.set()
        self._thread.join(timeout=10.0)

    def _run(self) -> None:
        while not self._stopped:
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                if self._fd is None or self._stopped:
                    continue
                try:
                    os.fsync(self._fd)
                except OSError as e:
                    self.error = e


@dataclass
class _Topic:
    name: str
    msgtype: str
    qos: Qos
    type_hash: str
    channel_id: int = 0


class _File:
    """One open MCAP file: its writer, what is on disk (``committed``) and what waits."""

    def __init__(self, path: Path, compress: bool):
        self.path = path
        self.stream = _Unbuffered(path)
        # the mcap Writer only calls write() and tell() on its stream (and close() when it
        # opened it itself); its annotation asks for a whole IO
        self.mcap = McapWriter(
            cast(IO[bytes], self.stream),
            chunk_size=2**62,  # chunks are cut by BagWriter
            compression=CompressionType.ZSTD if compress else CompressionType.NONE,
        )
        self.mcap.start(profile="ros2", library=f"maem_ros; mcap {mcap.__version__}")
        self.schemas: dict[str, int] = {}
        self.committed_bytes = self.stream.tell()
        self.committed = metadata.FileEntry(path.name)
        self.pending: dict[str, int] = {}
        self.pending_bytes = 0
        self.pending_since: float | None = None  # monotonic s of the oldest waiting message
        self.times: list[int] = []  # [first, last] log time on disk
        self.pending_times: list[int] = []


class BagWriter:
    """rosbag2 MCAP writer: topics registered on first use; ``close()`` finishes the files.

    ``compress`` (zstd chunks) is kept for the callers that pass only it; ``options`` sets
    everything (WriteOptions). ``durable`` fsyncs chunks (at most every chunk_duration s) and
    metadata.yaml. Not thread-safe: call write*/tick/close from one thread.
    """

    def __init__(
        self,
        path: str | Path,
        compress: bool = False,
        options: WriteOptions | None = None,
        durable: bool = True,
    ):
        self.path = Path(path)
        self.options = options if options is not None else WriteOptions(compress=compress)
        self.durable = durable
        try:
            self.path.mkdir(parents=True)
        except FileExistsError:
            raise FileExistsError(
                errno.EEXIST, f"bag {str(self.path)!r}: exists already, not overwriting"
            ) from None
        self._topics: dict[str, _Topic] = {}
        self.counts: dict[str, int] = {}  # messages written (incl. waiting in the open chunk)
        self._custom: dict[str, str] = {}
        self._done: list[metadata.FileEntry] = []
        self._done_counts: dict[str, int] = {}
        self._file: _File | None = None
        self._last_meta = self._last_sync = time.monotonic()
        self.failed: BagWriteError | None = None
        self._syncer = _Syncer() if durable else None
        self._guarded(self._open_file)

    # ---- public -------------------------------------------------------------------------------
    def add_topic(self, topic: str, msgtype: str, qos: Qos | None = None) -> None:
        """Register a topic (no-op if already registered with the same type)."""
        if topic in self._topics:
            if self._topics[topic].msgtype != msgtype:
                raise ValueError(
                    f"topic {topic!r}: already registered as {self._topics[topic].msgtype}, not {msgtype}"
                )
            return
        if not known_type(msgtype):
            raise ValueError(f"topic {topic!r}: message type {msgtype!r} is not in the ROS 2 Jazzy typestore")
        if qos is None:
            qos = QOS_SENSOR if is_image_type(msgtype) else QOS_RELIABLE
        self._topics[topic] = _Topic(topic, msgtype, qos, schema_text(msgtype)[1])
        self.counts[topic] = 0
        if self._file is not None:
            self._guarded(self._register, self._file, self._topics[topic])

    def write(self, topic: str, msg, stamp_ns: int, qos: Qos | None = None) -> None:
        """Serialise and write a rosbags or rclpy message at log time ``stamp_ns``."""
        self.write_raw(topic, msgtype_of(msg), serialize(msg), stamp_ns, qos)

    def write_raw(self, topic: str, msgtype: str, data: bytes, stamp_ns: int, qos: Qos | None = None) -> None:
        """Write already-serialised CDR bytes (BagWriteError once writing failed)."""
        if self.failed is not None:
            raise self.failed
        self.add_topic(topic, msgtype, qos)
        self._guarded(self._write, self._topics[topic], bytes(data), int(stamp_ns))

    def set_custom(self, key: str, value: str) -> None:
        """metadata.yaml custom_data entry (string value)."""
        if not isinstance(value, str):
            raise TypeError(f"custom data {key!r}: expected a string, got {type(value).__name__}")
        self._custom[key] = value

    def tick(self) -> None:
        """Write the open chunk once it is chunk_duration old, metadata.yaml once it is
        metadata_period old (call periodically, e.g. from a timer)."""
        if self.failed is None and self._file is not None:
            self._guarded(self._tick)

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    @property
    def files(self) -> list[str]:
        """Names of the files written so far (the open one last)."""
        return [f.path for f in self._done] + ([self._file.path.name] if self._file else [])

    def close(self) -> None:
        """Finish the open file (summary, footer) and write the final metadata.yaml."""
        try:
            if self._file is not None and self.failed is None:
                self._guarded(self._finish_file)
                self._guarded(self._write_metadata)
        finally:
            self._file = None
            if self._syncer is not None:
                self._syncer.stop()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- files ----------------------------------------------------------------------------------
    def _file_name(self, index: int) -> str:
        split = self.options.max_bag_duration > 0 or self.options.max_bag_size > 0
        return f"{self.path.name}_{index}.mcap" if split else f"{self.path.name}.mcap"

    def _current(self) -> _File:
        """The open file (writing steps run only while one is open)."""
        if self._file is None:
            raise ValueError(f"bag {str(self.path)!r}: no file open (the writer is closed)")
        return self._file

    def _open_file(self) -> None:
        path = self.path / self._file_name(len(self._done))
        try:
            self._file = _File(path, self.options.compress)
        except OSError:
            path.unlink(missing_ok=True)  # a file without its header holds nothing
            raise
        for topic in self._topics.values():
            self._register(self._file, topic)
        self._write_metadata()

    def _register(self, f: _File, topic: _Topic) -> None:
        if topic.msgtype not in f.schemas:
            f.schemas[topic.msgtype] = f.mcap.register_schema(
                topic.msgtype, "ros2msg", schema_text(topic.msgtype)[0].encode()
            )
        topic.channel_id = f.mcap.register_channel(
            topic.name, "cdr", f.schemas[topic.msgtype], {"offered_qos_profiles": dump_qos_v8([topic.qos])}
        )

    def _finish_file(self) -> None:
        f = self._current()
        self._flush_chunk()
        f.mcap.add_metadata(
            metadata.MCAP_METADATA_NAME,
            {metadata.MCAP_METADATA_KEY: metadata.dump(self._metadata(include_open=True))},
        )
        f.mcap.finish()
        if self._syncer is not None:
            self._syncer.forget()  # no background sync of this descriptor any more
            os.fsync(f.stream.fd)
        f.stream.close()
        self._done.append(f.committed)
        self._file = None

    def _split_due(self, stamp_ns: int) -> bool:
        f, o = self._current(), self.options
        if not f.times and not f.pending_times:
            return False
        first = min(f.times[:1] + f.pending_times[:1])
        too_long = o.max_bag_duration > 0 and stamp_ns - first >= o.max_bag_duration * 1e9
        too_big = o.max_bag_size > 0 and f.committed_bytes + f.pending_bytes >= o.max_bag_size * MB
        return too_long or too_big

    # ---- messages and chunks --------------------------------------------------------------------
    def _write(self, topic: _Topic, data: bytes, stamp_ns: int) -> None:
        if self._split_due(stamp_ns):
            self._finish_file()
            self._open_file()
        f = self._current()
        f.mcap.add_message(topic.channel_id, stamp_ns, data, stamp_ns)
        f.pending[topic.name] = f.pending.get(topic.name, 0) + 1
        f.pending_bytes += len(data) + 31  # + the Message record's header
        f.pending_times = [min(f.pending_times[:1] + [stamp_ns]), max(f.pending_times[1:] + [stamp_ns])]
        if f.pending_since is None:
            f.pending_since = time.monotonic()
        self.counts[topic.name] += 1
        if (
            f.pending_bytes >= self.options.chunk_size * MB
            or stamp_ns - f.pending_times[0] >= self.options.chunk_duration * 1e9
        ):
            self._flush_chunk()
        if time.monotonic() - self._last_meta >= self.options.metadata_period:
            self._write_metadata()

    def _tick(self) -> None:
        f, now = self._current(), time.monotonic()
        if f.pending_since is not None and now - f.pending_since >= self.options.chunk_duration:
            self._flush_chunk()
        if now - self._last_meta >= self.options.metadata_period:
            self._write_metadata()

    def _flush_chunk(self) -> None:
        """Write the open chunk and its message indexes; account it as on disk."""
        f = self._current()
        if not f.pending:
            return
        f.mcap.flush()
        f.committed_bytes = f.stream.tell()
        f.times = [min(f.times[:1] + f.pending_times[:1]), max(f.times[1:] + f.pending_times[1:])]
        f.committed.start_ns, f.committed.duration_ns = f.times[0], f.times[1] - f.times[0]
        f.committed.count += sum(f.pending.values())
        for topic, n in f.pending.items():
            self._done_counts[topic] = self._done_counts.get(topic, 0) + n
        f.pending, f.pending_bytes, f.pending_since, f.pending_times = {}, 0, None, []
        if self._syncer is not None:
            if self._syncer.error is not None:
                raise self._syncer.error
            if time.monotonic() - self._last_sync >= self.options.chunk_duration:
                self._syncer.request(f.stream.fd)
                self._last_sync = time.monotonic()

    # ---- metadata -------------------------------------------------------------------------------
    def _metadata(self, include_open: bool) -> metadata.Metadata:
        """What is on disk: finished files, the open file's whole chunks."""
        files = list(self._done) + ([self._file.committed] if self._file and include_open else [])
        topics = [
            metadata.TopicEntry(t.name, t.msgtype, [t.qos], self._done_counts.get(t.name, 0), t.type_hash)
            for t in self._topics.values()
        ]
        return metadata.Metadata(topics, files, dict(self._custom))

    def _write_metadata(self) -> None:
        metadata.write(self.path, self._metadata(include_open=True), self.durable)
        self._last_meta = time.monotonic()

    # ---- failures -------------------------------------------------------------------------------
    def _guarded(self, step, *args: Any) -> None:
        """Run a writing step; an OSError stops the writer (see _fail)."""
        try:
            step(*args)
        except BagWriteError:
            raise
        except OSError as e:
            self._fail(e)

    def _fail(self, e: OSError) -> None:
        f = self._file
        name = f.path.name if f is not None else "metadata.yaml"
        if self._syncer is not None:
            self._syncer.forget()
        if f is not None:
            try:  # keep what is whole: cut the partly written chunk off (frees its space)
                os.ftruncate(f.stream.fd, f.committed_bytes)
                f.stream.close()
            except OSError:
                pass
            self._done.append(f.committed)
            self._file = None
        try:
            metadata.write(self.path, self._metadata(include_open=False), self.durable)
            meta_note = "metadata.yaml updated"
        except OSError:
            meta_note = "metadata.yaml not updated (readers rebuild it)"
        kept = sum(x.count for x in self._done)
        ends = [x.start_ns + x.duration_ns for x in self._done if x.count]
        until = f", up to {_utc(max(ends))}" if ends else ""
        reason = e.strerror or str(e)
        self.failed = BagWriteError(
            e.errno,
            f"bag {str(self.path)!r}: writing {name} failed ({reason}): stopped; "
            f"{kept:,} messages in {len(self._done)} file(s) are readable{until} "
            f"({name} cut back to its last whole chunk, {meta_note})",
        )
        raise self.failed
