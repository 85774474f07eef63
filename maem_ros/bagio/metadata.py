"""rosbag2 ``metadata.yaml`` (format version 9, as rosbag2 Jazzy and rosbags write it): building,
writing atomically (temporary file + fsync + rename, so a crash leaves the old or the new file,
never half of one) and parsing. QoS profiles use rosbags' own dump/parse helpers."""

from __future__ import annotations

import copy
import functools
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

from maem_ros.core.errors import InputError

METADATA = "metadata.yaml"
VERSION = 9
#: the MCAP Metadata record rosbag2 writes into every finished file (YAML of the bag's metadata)
MCAP_METADATA_NAME = "rosbag2"
MCAP_METADATA_KEY = "serialized_metadata"


class BagError(InputError):
    """A bag that cannot be read: ``bag '<path>': <problem>`` on one line."""

    reason = "bad_bag"


@dataclass
class TopicEntry:
    """One topic: name, type, recorded QoS, message count, type hash (RIHS01, may be '')."""

    name: str
    msgtype: str
    qos: list[Qos] = field(default_factory=list)
    count: int = 0
    type_hash: str = ""


@dataclass
class FileEntry:
    """One storage file of a bag: relative path, first log time, duration (ns), messages."""

    path: str
    start_ns: int = 0
    duration_ns: int = 0
    count: int = 0


@dataclass
class Metadata:
    """What metadata.yaml says: topics (in order), files (in order), custom data."""

    topics: list[TopicEntry]
    files: list[FileEntry]
    custom: dict[str, str]
    compression: str = ""

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics)


def to_dict(meta: Metadata) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of ``meta``."""
    starts = [f.start_ns for f in meta.files if f.count]
    ends = [f.start_ns + f.duration_ns for f in meta.files if f.count]
    start = min(starts, default=0)
    return {
        "version": VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [f.path for f in meta.files],
        "duration": {"nanoseconds": max(ends, default=0) - start},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": meta.message_count,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": dump_qos_v9(list(t.qos)),
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.count,
            }
            for t in meta.topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": f.path,
                "starting_time": {"nanoseconds_since_epoch": f.start_ns},
                "duration": {"nanoseconds": f.duration_ns},
                "message_count": f.count,
            }
            for f in meta.files
        ],
        "custom_data": dict(meta.custom) or None,
        "ros_distro": "rosbags",
    }


def dump(meta: Metadata) -> str:
    """The text of metadata.yaml."""
    return yaml.safe_dump({"rosbag2_bagfile_information": to_dict(meta)}, sort_keys=True)


def write(folder: Path, meta: Metadata, durable: bool = True) -> None:
    """Replace ``folder/metadata.yaml`` atomically (temp file, fsync with ``durable``, rename).
    OSError (a full disk) leaves the previous metadata.yaml in place."""
    target = Path(folder) / METADATA
    tmp = target.with_name(f".{METADATA}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(dump(meta))
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


#: libyaml's loader when PyYAML has it (metadata.yaml holds the rig YAML: tens of kB)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _qos(value: Any) -> list[Qos]:
    """QoS profiles from metadata.yaml (a list, v9) or an MCAP channel / v8 (YAML text)."""
    if isinstance(value, str):
        return list(_qos_text(value))
    try:
        return parse_qos(value) if value else []
    except Exception:  # noqa: BLE001 - rosbags raises ReaderError/KeyError/TypeError: no QoS
        return []


@functools.lru_cache(maxsize=64)
def _qos_text(text: str) -> tuple[Qos, ...]:
    try:
        items = yaml.load(text, Loader=_LOADER) if text else []
        return tuple(parse_qos(items)) if items else ()
    except Exception:  # noqa: BLE001 - unreadable QoS text: none recorded
        return ()


def from_dict(info: dict[str, Any]) -> Metadata:
    """Metadata from a ``rosbag2_bagfile_information`` mapping (KeyError/TypeError when a
    required field is missing)."""
    topics = []
    for item in info.get("topics_with_message_count") or []:
        tm = item["topic_metadata"]
        topics.append(
            TopicEntry(
                tm["name"],
                tm["type"],
                _qos(tm.get("offered_qos_profiles")),
                int(item.get("message_count", 0)),
                str(tm.get("type_description_hash") or ""),
            )
        )
    files = []
    listed = {f["path"]: f for f in info.get("files") or []}
    for rel in info.get("relative_file_paths") or list(listed):
        f = listed.get(rel, {})
        files.append(
            FileEntry(
                str(rel),
                int((f.get("starting_time") or {}).get("nanoseconds_since_epoch", 0)),
                int((f.get("duration") or {}).get("nanoseconds", 0)),
                int(f.get("message_count", 0)),
            )
        )
    custom = {str(k): str(v) for k, v in (info.get("custom_data") or {}).items()}
    return Metadata(topics, files, custom, str(info.get("compression_format") or ""))


def parse(text: str) -> Metadata:
    """Metadata from metadata.yaml text, or from a file's serialized_metadata (which is the
    inner mapping)."""
    data = yaml.load(text, Loader=_LOADER)
    if not isinstance(data, dict):
        raise TypeError(f"expected a mapping, got {type(data).__name__}")
    return from_dict(data.get("rosbag2_bagfile_information", data))


def load(folder: Path) -> Metadata | None:
    """``folder/metadata.yaml`` parsed; None when there is none; BagError (one line) when it
    is not a rosbag2 metadata file."""
    path = Path(folder) / METADATA
    if not path.is_file():
        return None
    try:
        meta = _parse_file(str(path.resolve()), path.stat().st_mtime_ns, path.stat().st_size)
    except (
        OSError,
        UnicodeDecodeError,
        yaml.YAMLError,
        KeyError,
        TypeError,
        ValueError,
        AttributeError,
    ) as e:
        problem = " ".join(str(e).split()) or type(e).__name__
        raise BagError(
            f"bag {str(folder)!r}: unreadable metadata.yaml ({type(e).__name__}: "
            f"{problem[:160]}); `maem-bag recover` rebuilds it from the MCAP files "
            f"once it is removed"
        ) from None
    meta = copy.deepcopy(meta)
    if meta.compression:
        raise BagError(
            f"bag {str(folder)!r}: file compression {meta.compression!r} is not "
            f"supported (MCAP chunk compression is)"
        )
    return meta


@functools.lru_cache(maxsize=16)
def _parse_file(path: str, mtime_ns: int, size: int) -> Metadata:
    """parse() of a file, cached while it is unchanged (readers open a bag several times)."""
    with open(path, encoding="utf-8") as f:
        return parse(f.read())
