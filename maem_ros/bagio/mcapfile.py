"""One MCAP storage file of a bag, read with the ``mcap`` library only: is it complete (footer and
summary) or cut short (a crash, a full disk, a copy that stopped), what it holds, its messages.

A complete file is read through its summary (chunk indexes, statistics) with mcap's
SeekingReader. A cut file is read with mcap's StreamReader record by record: every chunk that
was written whole (its record length is there and, when the writer stored one, its CRC matches)
is kept; reading stops at the first record that is cut or damaged. A cut chunk never yields a
message (StreamReader raises EndOfFile before returning a record shorter than its declared
length), so nothing garbled is returned. Scans are cached per (path, size, mtime).
"""

from __future__ import annotations

import heapq
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import Qos

from maem_ros.bagio import metadata
from maem_ros.bagio.metadata import BagError

MAGIC = b"\x89MCAP0\r\n"
#: errors of a damaged or cut file the mcap library raises while reading records
READ_ERRORS = (
    McapError,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    OSError,
    MemoryError,
    UnicodeDecodeError,
    struct.error,
)


@dataclass(frozen=True)
class Topic:
    """A channel of a file: topic, message type (schema name), recorded QoS."""

    name: str
    msgtype: str
    qos: tuple[Qos, ...] = ()


@dataclass
class FileScan:
    """What one .mcap file holds.

    ``complete``: it has its summary and footer. For a cut file, ``good_bytes`` is where its
    last whole record ends (what ``maem-bag recover`` keeps) and ``problem`` says why reading
    stopped. ``chunk_starts`` (cut files): first log time of every whole chunk in file order,
    for reading them back in log-time order.
    """

    path: Path
    size: int
    complete: bool
    topics: dict[int, Topic] = field(default_factory=dict)  # channel id -> topic
    counts: dict[str, int] = field(default_factory=dict)  # topic -> messages
    start_ns: int | None = None
    end_ns: int | None = None  # inclusive
    good_bytes: int = 0
    problem: str = ""
    chunk_starts: list[int] = field(default_factory=list)
    compression: str = ""
    indexed: bool = False  # read through the summary's chunk indexes
    rosbag2_metadata: str | None = None  # the serialized_metadata record, when written

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def note(self, log_time: int, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.start_ns = log_time if self.start_ns is None else min(self.start_ns, log_time)
        self.end_ns = log_time if self.end_ns is None else max(self.end_ns, log_time)


def _qos_of(channel: Channel) -> tuple[Qos, ...]:
    text = channel.metadata.get("offered_qos_profiles", "")
    return tuple(metadata._qos(text))


def _topic(channel: Channel, schemas: dict[int, Schema]) -> Topic:
    schema = schemas.get(channel.schema_id)
    return Topic(channel.topic, schema.name if schema is not None else "", _qos_of(channel))


def check_magic(path: Path) -> None:
    """BagError unless the file starts with the MCAP magic (or is a cut-off start of it)."""
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if not MAGIC.startswith(head):
        raise BagError(
            f"bag {str(path.parent)!r}: {path.name} is not an MCAP file (it starts with {head[:8]!r})"
        )


_CACHE: dict[tuple[str, int, int], FileScan] = {}


def scan(path: Path) -> FileScan:
    """The contents of ``path`` (cached while the file is unchanged); BagError when it is not
    an MCAP file."""
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        check_magic(path)
        result = _scan_summary(path, st.st_size)
        _CACHE[key] = result if result is not None else _scan_stream(path, st.st_size)
    return _CACHE[key]


def _scan_summary(path: Path, size: int) -> FileScan | None:
    """A complete file from its summary (None when it has no usable summary/statistics)."""
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return None
            meta = next(
                (
                    m.metadata.get(metadata.MCAP_METADATA_KEY)
                    for m in reader.iter_metadata()
                    if m.name == metadata.MCAP_METADATA_NAME
                ),
                None,
            )
    except READ_ERRORS:
        return None
    stats = summary.statistics
    out = FileScan(path, size, True, good_bytes=size, indexed=True, rosbag2_metadata=meta)
    out.topics = {cid: _topic(c, summary.schemas) for cid, c in summary.channels.items()}
    for cid, n in stats.channel_message_counts.items():
        name = out.topics[cid].name
        out.counts[name] = out.counts.get(name, 0) + int(n)
    for t in out.topics.values():
        out.counts.setdefault(t.name, 0)
    if stats.message_count:
        out.start_ns, out.end_ns = int(stats.message_start_time), int(stats.message_end_time)
    out.compression = next((c.compression for c in summary.chunk_indexes), "")
    return out


def _scan_stream(path: Path, size: int) -> FileScan:
    """A cut (or summary-less) file record by record, up to its first cut/damaged record."""
    out = FileScan(path, size, False)
    schemas: dict[int, Schema] = {}
    with open(path, "rb") as f:
        # StreamReader reads this (buffered) file itself, exactly a record's bytes at a time:
        # f.tell() is the offset where the last record read ends
        try:
            for record in StreamReader(f, emit_chunks=True, validate_crcs=True).records:
                if isinstance(record, Chunk):
                    _take_chunk(out, schemas, record)
                else:
                    _take_record(out, schemas, record)
                out.good_bytes = f.tell()
                if isinstance(record, Footer):
                    out.complete, out.good_bytes = True, size
        except READ_ERRORS as e:
            clean = f.tell() == out.good_bytes
            out.problem = (
                ("ends without its summary" if clean else "ends inside a record")
                if isinstance(e, EndOfFile)
                else f"damaged record after byte {out.good_bytes:,}: {type(e).__name__} {str(e)[:80]}"
            )
    if out.good_bytes < len(MAGIC):
        out.good_bytes = 0
    return out


def _take_record(out: FileScan, schemas: dict[int, Schema], record) -> None:
    if isinstance(record, Schema):
        schemas[record.id] = record
    elif isinstance(record, Channel):
        out.topics[record.id] = _topic(record, schemas)
        out.counts.setdefault(record.topic, 0)
    elif isinstance(record, Message):
        out.note(record.log_time, out.topics[record.channel_id].name)
    elif isinstance(record, Metadata) and record.name == metadata.MCAP_METADATA_NAME:
        out.rosbag2_metadata = record.metadata.get(metadata.MCAP_METADATA_KEY)


def _take_chunk(out: FileScan, schemas: dict[int, Schema], chunk: Chunk) -> None:
    """Count a whole chunk (CRC checked when stored); its records are committed together."""
    records = breakup_chunk(chunk, validate_crc=True)
    for record in records:
        _take_record(out, schemas, record)
    if any(isinstance(r, Message) for r in records):
        out.chunk_starts.append(int(chunk.message_start_time))
    out.compression = out.compression or chunk.compression


# ---- messages ------------------------------------------------------------------------------------
#: (log time ns, topic, message type, CDR bytes)
Item = tuple[int, str, str, bytes]


def messages(
    fs: FileScan, topics: Iterable[str] | None = None, start_ns: int | None = None, stop_ns: int | None = None
) -> Iterator[Item]:
    """The file's messages in log-time order, only ``topics`` and log times in [start, stop)."""
    wanted = None if topics is None else set(topics)
    if fs.indexed:
        yield from _indexed_messages(fs, wanted, start_ns, stop_ns)
    else:
        yield from _streamed_messages(fs, wanted, start_ns, stop_ns)


def _indexed_messages(
    fs: FileScan, wanted: set[str] | None, start_ns: int | None, stop_ns: int | None
) -> Iterator[Item]:
    with open(fs.path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, msg in reader.iter_messages(
            topics=None if wanted is None else sorted(wanted),
            log_time_order=True,
            starting_at=start_ns,
            ending_before=stop_ns,
        ):
            yield (int(msg.log_time), channel.topic, schema.name if schema else "", bytes(msg.data))


def _streamed_messages(
    fs: FileScan, wanted: set[str] | None, start_ns: int | None, stop_ns: int | None
) -> Iterator[Item]:
    """Whole chunks in file order, merged into log-time order: a message is released once no
    later chunk can start before it (suffix minimum of the chunk start times from the scan).
    Messages outside chunks (an unchunked file) are released at the end."""
    later_min = list(fs.chunk_starts) + [2**64]
    for i in range(len(later_min) - 2, -1, -1):
        later_min[i] = min(later_min[i], later_min[i + 1])
    heap: list[tuple[int, int, Item]] = []
    seq, n_chunk = 0, 0
    schemas: dict[int, Schema] = {}
    topics: dict[int, Topic] = {}
    with open(fs.path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True, validate_crcs=True).records
        while f.tell() < fs.good_bytes:  # as far as the scan found whole records
            try:
                record = next(reader)
                records = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except (StopIteration, *READ_ERRORS):
                break
            for r in records:
                if isinstance(r, Schema):
                    schemas[r.id] = r
                elif isinstance(r, Channel):
                    topics[r.id] = _topic(r, schemas)
                elif isinstance(r, Message):
                    t = topics[r.channel_id]
                    if (
                        (wanted is None or t.name in wanted)
                        and (start_ns is None or r.log_time >= start_ns)
                        and (stop_ns is None or r.log_time < stop_ns)
                    ):
                        heapq.heappush(
                            heap, (r.log_time, seq, (int(r.log_time), t.name, t.msgtype, bytes(r.data)))
                        )
                        seq += 1
            if isinstance(record, Chunk) and any(isinstance(r, Message) for r in records):
                n_chunk = min(n_chunk + 1, len(later_min) - 1)
                while heap and heap[0][0] < later_min[n_chunk]:
                    yield heapq.heappop(heap)[2]
    while heap:
        yield heapq.heappop(heap)[2]


def is_mcap_name(name: str) -> bool:
    return name.endswith(".mcap") and not name.startswith(".")


def split_index(path: Path) -> tuple[int, str]:
    """Sort key of a bag's files: rosbag2's ``<name>_<N>.mcap`` by N, others by name."""
    stem = path.name[: -len(".mcap")]
    head, _, tail = stem.rpartition("_")
    return (int(tail), path.name) if head and tail.isdigit() else (-1, path.name)
