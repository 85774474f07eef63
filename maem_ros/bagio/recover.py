"""Repairing a bag after a crash (``maem-bag recover``), like ``ros2 bag reindex`` plus
``mcap recover``: every cut file is rewritten up to its last whole chunk with the mcap library
(StreamReader in, Writer out: summary, indexes and footer), and metadata.yaml is rebuilt from
the MCAP files (QoS and custom data kept from the old metadata.yaml or the files' own rosbag2
metadata records).

In place (no ``out``), a cut file is replaced only once its rewrite is complete and synced;
with ``out`` the bag is copied there (whole files as they are).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from maem_ros.bagio import mcapfile, metadata, reader
from maem_ros.bagio.mcapfile import FileScan
from maem_ros.bagio.metadata import BagError


@dataclass
class FileResult:
    """One file: kept as it was, or rewritten (messages kept, bytes of the cut tail dropped)."""

    name: str
    rewritten: bool
    messages: int
    dropped_bytes: int = 0


@dataclass
class RecoverReport:
    """What ``recover`` did: per topic messages recovered and messages known lost (listed in
    the old metadata.yaml but not readable; unknown for a chunk cut before its messages were
    counted), per file what happened."""

    bag: Path
    recovered: dict[str, int]
    listed: dict[str, int]
    files: list[FileResult] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def lost(self, topic: str) -> int:
        return max(0, self.listed.get(topic, 0) - self.recovered.get(topic, 0))

    @property
    def message_count(self) -> int:
        return sum(self.recovered.values())


def _copy_messages(src: FileScan, dst: Path) -> int:
    """Rewrite the whole records of ``src`` into a new complete MCAP ``dst``; messages kept."""
    n = 0
    compression = CompressionType.ZSTD if src.compression == "zstd" else CompressionType.NONE
    with open(src.path, "rb") as f, open(dst, "xb") as out:
        writer = McapWriter(out, compression=compression)
        writer.start(profile="ros2", library="maem_ros recover")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        # StreamReader reads f itself, a record at a time: f.tell() is where the last one ends
        records = StreamReader(f, emit_chunks=True, validate_crcs=True).records
        while f.tell() < src.good_bytes:
            try:
                record = next(records)
                items = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except (StopIteration, *mcapfile.READ_ERRORS):
                break
            for r in items:
                if isinstance(r, Schema) and r.id not in schema_ids:
                    schema_ids[r.id] = writer.register_schema(r.name, r.encoding, r.data)
                elif isinstance(r, Channel) and r.id not in channel_ids:
                    channel_ids[r.id] = writer.register_channel(
                        r.topic, r.message_encoding, schema_ids.get(r.schema_id, 0), r.metadata
                    )
                elif isinstance(r, Message):
                    writer.add_message(
                        channel_ids[r.channel_id], r.log_time, r.data, r.publish_time, r.sequence
                    )
                    n += 1
        if src.rosbag2_metadata:
            writer.add_metadata(
                metadata.MCAP_METADATA_NAME, {metadata.MCAP_METADATA_KEY: src.rosbag2_metadata}
            )
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    return n


def _rebuilt_metadata(
    info: reader.BagInfo, old: metadata.Metadata | None, scans: list[FileScan]
) -> metadata.Metadata:
    hashes = {t.name: t.type_hash for t in old.topics} if old is not None else {}
    topics = [
        metadata.TopicEntry(
            name, msgtype, list(info.qos.get(name, [])), info.counts.get(name, 0), hashes.get(name, "")
        )
        for name, msgtype in info.topics.items()
    ]
    files = [
        metadata.FileEntry(
            fs.path.name, fs.start_ns or 0, (fs.end_ns or 0) - (fs.start_ns or 0), fs.message_count
        )
        for fs in scans
    ]
    return metadata.Metadata(topics, files, dict(info.custom))


def recover(bag: str | Path, out: str | Path | None = None) -> RecoverReport:
    """Repair ``bag`` in place, or write the repaired copy to ``out`` (must not exist)."""
    bag = Path(bag)
    old = metadata.load(bag) if bag.is_dir() else None
    info = reader.open_info(bag)
    target = bag if out is None else Path(out)
    if out is not None:
        if target.exists():
            raise BagError(f"--out {str(target)!r}: exists already")
        target.mkdir(parents=True)
    report = RecoverReport(target, dict(info.counts), dict(info.listed))
    report.problems = [info.damage] if info.damage else []
    scans = []
    for fs in info.files:
        dst = target / fs.path.name
        if fs.complete:
            if out is not None:
                shutil.copy2(fs.path, dst)
            report.files.append(FileResult(fs.path.name, False, fs.message_count))
        else:
            tmp = target / f".{fs.path.name}.recover"
            tmp.unlink(missing_ok=True)
            n = _copy_messages(fs, tmp)
            os.replace(tmp, dst)
            report.files.append(FileResult(fs.path.name, True, n, fs.size - fs.good_bytes))
        scans.append(mcapfile.scan(dst))
    metadata.write(target, _rebuilt_metadata(info, old, scans))
    return report


def format_report(r: RecoverReport) -> list[str]:
    """Lines for the user: per file, per topic (recovered, lost), a total."""
    lines = []
    for f in r.files:
        what = (
            (
                f"rewritten up to its last whole chunk: {f.messages:,} messages kept, "
                f"{f.dropped_bytes:,} bytes of a cut chunk dropped"
            )
            if f.rewritten
            else f"complete, kept as it is ({f.messages:,} messages)"
        )
        lines.append(f"{f.name}: {what}")
    width = max((len(t) for t in r.recovered), default=5)
    lines.append(f"{'topic':<{width}}  recovered  lost")
    for topic, n in r.recovered.items():
        lost = r.lost(topic)
        lines.append(
            f"{topic:<{width}}  {n:>9,}  {lost:>4,}"
            if topic in r.listed
            else f"{topic:<{width}}  {n:>9,}     ?"
        )
    total_lost = sum(r.lost(t) for t in r.recovered)
    lost_note = (
        f"{total_lost:,} known lost (listed in the old metadata.yaml)"
        if r.listed
        else "losses per topic unknown (no metadata.yaml to compare with)"
    )
    cut = sum(f.dropped_bytes for f in r.files)
    tail = f"; {cut:,} bytes of cut chunks dropped (their messages cannot be counted)" if cut else ""
    lines.append(f"recovered {r.message_count:,} messages into {r.bag}; {lost_note}{tail}")
    return lines
