"""Opening a bag for reading, tolerant of what a crash leaves (the one home of that logic).

A bag is a folder with ``metadata.yaml`` and MCAP files. Every reader of the project (maem-play,
maem-export, maem-demo, the report and evaluation tools, maem-bag) opens bags here, so all of
them accept the same damage and refuse the same garbage:

* accepted, with one warning line (``BagInfo.damage``): a file cut short (a killed recorder, a
  power cut, a full disk, a copy that stopped) -- every whole chunk is read, the rest is lost;
  a missing ``metadata.yaml`` -- topics, counts and times come from the MCAP files; a file
  in the folder that metadata.yaml does not list yet (a split just before a crash);
* refused with one line (BagError): no such folder, a folder with neither metadata.yaml nor
  .mcap files, a file that is not MCAP, a listed file that is missing, an unreadable
  metadata.yaml, a bag without a single complete message.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.interfaces import Qos

from maem_ros.bagio import mcapfile, metadata
from maem_ros.bagio.mcapfile import FileScan
from maem_ros.bagio.messages import CUSTOM_GT_CONVENTION, CUSTOM_RIG, CUSTOM_SCENE, SCENE_TOPIC, deserialize  # noqa: F401
from maem_ros.bagio.metadata import BagError


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes

    def decode(self):
        return deserialize(self.data, self.msgtype)


@dataclass
class BagInfo:
    """What a bag holds (counting only messages that can be read back).

    ``damage`` is one line (empty for a sound bag) saying what was cut or missing and how many
    messages are readable; readers print it as a warning. ``files`` are the scans in order.
    """

    topics: dict[str, str]  # topic -> msgtype
    counts: dict[str, int]
    start_ns: int
    end_ns: int  # last message log time (inclusive)
    message_count: int
    custom: dict[str, str]
    qos: dict[str, list[Qos]]  # topic -> offered QoS profiles recorded
    damage: str = ""
    files: list[FileScan] = field(default_factory=list)
    listed: dict[str, int] = field(default_factory=dict)  # metadata.yaml counts (if any)


def bag_files(path: Path, meta: metadata.Metadata | None) -> tuple[list[Path], list[str]]:
    """(the bag's MCAP files in order, problems): listed ones first, then unlisted .mcap files
    of the folder (by split index). BagError when a listed file is missing or nothing is
    there."""
    if not path.exists():
        raise BagError(f"bag {str(path)!r}: not a rosbag2 folder (no such file or directory)")
    if not path.is_dir():
        raise BagError(f"bag {str(path)!r}: not a rosbag2 folder (a file; give its folder)")
    present = sorted((p for p in path.iterdir() if mcapfile.is_mcap_name(p.name)), key=mcapfile.split_index)
    problems = []
    if meta is None:
        if not present:
            raise BagError(f"bag {str(path)!r}: not a rosbag2 folder (no metadata.yaml and no .mcap file)")
        problems.append("metadata.yaml missing (rebuilt from the MCAP files)")
        return present, problems
    listed = [path / f.path for f in meta.files]
    for p in listed:
        if not p.is_file():
            raise BagError(f"bag {str(path)!r}: {p.name} listed in metadata.yaml is missing")
    extra = [p for p in present if p not in listed]
    if extra:
        problems.append(f"{', '.join(p.name for p in extra)} not in metadata.yaml")
    return listed + extra, problems


def _custom(meta: metadata.Metadata | None, scans: list[FileScan]) -> dict[str, str]:
    """custom_data of metadata.yaml, else of the last file that recorded the bag's metadata."""
    if meta is not None:
        return dict(meta.custom)
    for fs in reversed(scans):
        if fs.rosbag2_metadata:
            try:
                return dict(metadata.parse(fs.rosbag2_metadata).custom)
            except Exception:  # noqa: BLE001 - a damaged record: no custom data from it
                continue
    return {}


def _damage_line(
    path: Path, scans: list[FileScan], problems: list[str], n: int, meta: metadata.Metadata | None
) -> str:
    cut = [fs for fs in scans if not fs.complete]
    if not cut and not problems:
        return ""
    parts = [
        f"{fs.path.name} is cut short ({fs.problem or 'no summary'}; "
        f"{fs.message_count:,} whole messages, {fs.size - fs.good_bytes:,} bytes after "
        f"them unreadable)"
        for fs in cut
    ] + problems
    listed = (
        f" of {meta.message_count:,} listed in metadata.yaml"
        if meta is not None and meta.message_count > n
        else ""
    )
    return (
        f"bag {str(path)!r}: {'; '.join(parts)}: reading the {n:,} complete messages"
        f"{listed}; `maem-bag recover {path}` repairs it"
    )


def open_info(path: str | Path) -> BagInfo:
    """Topics, counts, time range, custom data, recorded QoS and damage of a bag (BagError,
    one line, when it is no bag or holds no complete message)."""
    path = Path(path)
    meta = metadata.load(path) if path.is_dir() else None
    files, problems = bag_files(path, meta)
    scans = [mcapfile.scan(p) for p in files]
    topics: dict[str, str] = {}
    qos: dict[str, list[Qos]] = {}
    for t in meta.topics if meta is not None else []:
        topics[t.name], qos[t.name] = t.msgtype, list(t.qos)
    counts = {t: 0 for t in topics}
    for fs in scans:
        for topic in fs.topics.values():
            topics.setdefault(topic.name, topic.msgtype)
            qos.setdefault(topic.name, list(topic.qos))
        for name, c in fs.counts.items():
            counts[name] = counts.get(name, 0) + c
    n = sum(counts.values())
    if n == 0 and (problems or any(not fs.complete for fs in scans)):
        why = problems + [f"{fs.path.name} {fs.problem or 'empty'}" for fs in scans if not fs.complete]
        raise BagError(f"bag {str(path)!r}: no complete message ({'; '.join(why)})")
    starts = [fs.start_ns for fs in scans if fs.start_ns is not None]
    ends = [fs.end_ns for fs in scans if fs.end_ns is not None]
    listed = {t.name: t.count for t in meta.topics} if meta is not None else {}
    return BagInfo(
        topics,
        counts,
        min(starts, default=0),
        max(ends, default=0),
        n,
        _custom(meta, scans),
        qos,
        _damage_line(path, scans, problems, n, meta),
        scans,
        listed,
    )


def read_messages(
    path: str | Path,
    topics: Iterable[str] | None = None,
    start_ns: int | None = None,
    stop_ns: int | None = None,
    info: BagInfo | None = None,
) -> Iterator[BagMessage]:
    """Messages in log-time order, optionally only ``topics`` and log times in [start, stop)
    (every complete message of a damaged bag; ``info`` saves opening it again)."""
    info = info if info is not None else open_info(path)
    wanted = None if topics is None else set(topics)
    if wanted is not None and not wanted & set(info.topics):
        return
    streams = [mcapfile.messages(fs, wanted, start_ns, stop_ns) for fs in info.files if fs.message_count]
    for log_time, topic, msgtype, data in heapq.merge(*streams, key=lambda m: m[0]):
        yield BagMessage(topic, msgtype or info.topics.get(topic, ""), log_time, data)


def custom_data(path: str | Path) -> dict[str, str]:
    """metadata.yaml custom_data (empty dict when absent)."""
    return open_info(path).custom


def read_scene(path: str | Path) -> dict | None:
    """The scene description recorded by make_bag (custom data, else the /maem/scene message)."""
    info = open_info(path)
    if CUSTOM_SCENE in info.custom:
        return json.loads(info.custom[CUSTOM_SCENE])
    for msg in read_messages(path, [SCENE_TOPIC], info=info):
        return json.loads(msg.decode().data)
    return None


def read_scene_config(path: str | Path) -> dict | None:
    """The simulator's SceneConfig dict (scene.json ``scene_config``) recorded in a bag, or None.

    This is what the synthetic frontend backend takes as ``scene_dict`` (as JSON).
    """
    scene = read_scene(path)
    return None if scene is None else scene.get("scene_config")


def read_rig_yaml(path: str | Path) -> str | None:
    """Rig YAML text recorded by make_bag in custom data (None if absent)."""
    return custom_data(path).get(CUSTOM_RIG)
