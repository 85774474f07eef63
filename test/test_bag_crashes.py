"""Bags that survive crashes, without ROS: the writer's bounded chunks, splitting and full-disk
stop; cut files read back exactly up to their last whole chunk (random offsets); maem-bag info /
recover and the readers (maem-export, maem-demo's bag reading) on cut bags and garbage."""
from __future__ import annotations

import random
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rosbags.rosbag2 import Reader

from maem_ros import bagio
from maem_ros.tools.bags import record_faults

REPO = Path(__file__).resolve().parents[1]
DEMO_BAG = REPO / "bags" / "demo"
BIN = Path(sys.executable).parent
needs_demo = pytest.mark.skipif(not (DEMO_BAG / "metadata.yaml").is_file(),
                                reason="no committed bags/demo in this checkout")


def cli(name: str, *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """A console script of this venv, as a user runs it."""
    return subprocess.run([str(BIN / name), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout_s)


def one_line(proc: subprocess.CompletedProcess, code: int = 2) -> str:
    lines = [ln for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
    assert proc.returncode == code, (proc.returncode, lines)
    assert len(lines) == 1 and "Traceback" not in proc.stderr, lines
    return lines[0]


@pytest.fixture(scope="module")
def demo_messages() -> list[bagio.BagMessage]:
    if not (DEMO_BAG / "metadata.yaml").is_file():
        pytest.skip("no committed bags/demo in this checkout")
    return list(bagio.read_messages(DEMO_BAG))


@pytest.fixture(scope="module")
def written(tmp_path_factory, demo_messages) -> Path:
    """bags/demo rewritten by BagWriter (0.5 s / 1 MB chunks, uncompressed: as maem-record)."""
    return record_faults.cut_bag(DEMO_BAG, tmp_path_factory.mktemp("written"))


def as_tuples(msgs) -> list[tuple[str, int, bytes]]:
    return [(m.topic, m.log_time_ns, m.data) for m in msgs]


# ---- the writer ------------------------------------------------------------------------------
def test_open_chunk_reaches_the_disk_after_chunk_duration(tmp_path):
    """A message waits in memory at most chunk_duration; the folder a crash would leave (the
    writer never closed) is a readable bag with metadata.yaml from the start."""
    opts = bagio.WriteOptions(chunk_duration=0.2, metadata_period=0.2)
    w = bagio.BagWriter(tmp_path / "bag", options=opts, durable=False)
    assert bagio.metadata.load(tmp_path / "bag").files[0].path == "bag.mcap"  # from the start
    w.write("/a", bagio.string_msg("first"), 1_000)
    crashed = tmp_path / "crashed"
    shutil.copytree(tmp_path / "bag", crashed)  # now: still in memory
    with pytest.raises(bagio.BagError, match="no complete message"):
        bagio.bag_info(crashed)
    time.sleep(0.25)
    w.tick()
    shutil.rmtree(crashed)
    shutil.copytree(tmp_path / "bag", crashed)
    info = bagio.bag_info(crashed)
    assert info.counts == {"/a": 1} and not info.files[0].complete
    assert "cut short" in info.damage and "maem-bag recover" in info.damage
    assert [m.decode().data for m in bagio.read_messages(crashed)] == ["first"]
    assert bagio.metadata.load(crashed).message_count == 1  # what is on disk, listed
    w.close()
    assert bagio.bag_info(tmp_path / "bag").damage == ""


@pytest.mark.slow
def test_split_by_duration_and_size_read_by_rosbags_too(tmp_path, demo_messages):
    info = bagio.bag_info(DEMO_BAG)
    for name, opts, files in [("dur", bagio.WriteOptions(max_bag_duration=0.3), 4),
                              ("size", bagio.WriteOptions(max_bag_size=5, compress=True), None)]:
        out = tmp_path / name
        with bagio.BagWriter(out, options=opts, durable=False) as w:
            for m in demo_messages:
                w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, info.qos[m.topic][0])
        got = bagio.bag_info(out)
        names = [fs.path.name for fs in got.files]
        assert names == [f"{name}_{i}.mcap" for i in range(len(names))]
        assert all(fs.complete for fs in got.files) and got.damage == ""
        if files is not None:
            assert len(names) == files
            spans = [(fs.end_ns - fs.start_ns) / 1e9 for fs in got.files]
            assert max(spans) < 0.3, spans
        else:
            assert len(names) >= 2 and all(fs.size <= 5.5e6 for fs in got.files)
        meta = bagio.metadata.load(out)
        assert [f.path for f in meta.files] == names and meta.message_count == len(demo_messages)
        assert as_tuples(bagio.read_messages(out)) == as_tuples(demo_messages)
        with Reader(out) as r:  # the standard reader agrees
            assert sorted((c.topic, t, bytes(d)) for c, t, d in r.messages()) == \
                sorted(as_tuples(demo_messages))
            qos = {c.topic: c.ext.offered_qos_profiles for c in r.connections}
            assert qos[bagio.SCENE_TOPIC][0].durability == bagio.QosDurability.TRANSIENT_LOCAL


def test_file_size_limit_stops_writing_with_the_bag_readable(tmp_path, demo_messages):
    """EFBIG (as ENOSPC): one error line naming the bag, the file cut back to its last whole
    chunk, metadata.yaml saying so; later writes refused."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    w = bagio.BagWriter(tmp_path / "bag", durable=False)
    resource.setrlimit(resource.RLIMIT_FSIZE, (5_000_000, hard))
    try:
        with pytest.raises(bagio.BagWriteError) as err:
            for m in demo_messages:
                w.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    line = err.value.strerror
    assert "\n" not in line and str(tmp_path / "bag") in line and "File too large" in line
    said = int(line.split("stopped; ")[1].split(" messages")[0].replace(",", ""))
    info = bagio.bag_info(tmp_path / "bag")
    assert info.message_count == said > 0
    assert as_tuples(bagio.read_messages(tmp_path / "bag")) == as_tuples(demo_messages[:said])
    assert bagio.metadata.load(tmp_path / "bag").message_count == said
    with pytest.raises(bagio.BagWriteError):
        w.write_raw("/x", bagio.STRING, bagio.serialize(bagio.string_msg("x")), 1)
    w.close()


# ---- cut files -------------------------------------------------------------------------------
def test_cut_at_random_offsets_reads_every_whole_chunk_and_nothing_else(tmp_path, written):
    """Every message of a chunk that ends before the cut comes back byte-identical, nothing
    else (none garbled, none from the cut chunk); with or without metadata.yaml."""
    last = bagio.bag_info(written).files[-1]
    ends = [end for end, _ in record_faults.chunk_contents(last.path)]
    rng = random.Random(7)
    offsets = [0, 5, 8, ends[0] - 1, ends[0], ends[0] + 1, last.size - 1] + \
        [rng.randrange(8, last.size) for _ in range(10)]
    for k, off in enumerate(offsets):
        r = record_faults.cut_run(written, tmp_path / "cut", off, drop_metadata=k % 2 == 1)
        assert r.ok, r
        assert bool(r.refused) == (r.expected == 0), r
        if r.refused:
            assert "no complete message" in r.refused and "\n" not in r.refused


@needs_demo
def test_cut_committed_bag_without_crcs(tmp_path):
    """bags/demo was written by rosbags (chunks without CRCs): cut it, still exact."""
    size = (DEMO_BAG / "demo.mcap").stat().st_size
    for off in (size // 3, size * 2 // 3, size - 100):
        r = record_faults.cut_run(DEMO_BAG, tmp_path / "cut", off)
        assert r.ok and r.got > 0, r


def _cut_demo(tmp_path: Path, fraction: float, metadata: bool = True) -> Path:
    bag = tmp_path / "cutdemo"
    bag.mkdir()
    if metadata:
        shutil.copy(DEMO_BAG / "metadata.yaml", bag)
    data = (DEMO_BAG / "demo.mcap").read_bytes()
    (bag / "demo.mcap").write_bytes(data[:int(len(data) * fraction)])
    return bag


# ---- the command line ------------------------------------------------------------------------
@needs_demo
def test_maem_bag_info_and_recover_on_a_cut_bag(tmp_path):
    bag = _cut_demo(tmp_path, 0.7)
    n = bagio.bag_info(bag).message_count
    info = cli("maem-bag", "info", bag)
    assert info.returncode == 0, info.stderr
    assert "CUT SHORT" in info.stdout and f"messages:  {n:,}" in info.stdout
    assert "/camera_0/image_raw/compressed" in info.stdout and "(metadata.yaml: 30)" in info.stdout
    rec = cli("maem-bag", "recover", bag, "--out", tmp_path / "fixed")
    assert rec.returncode == 0, rec.stderr
    assert "demo.mcap: rewritten up to its last whole chunk" in rec.stdout
    lost = {ln.split()[0]: (int(ln.split()[1]), int(ln.split()[2])) for ln in
            rec.stdout.splitlines() if ln.startswith("/camera_0/")}
    assert all(got + gone == 30 for got, gone in lost.values()), lost
    fixed = bagio.bag_info(tmp_path / "fixed")
    assert fixed.damage == "" and all(fs.complete for fs in fixed.files)
    assert fixed.custom == bagio.bag_info(DEMO_BAG).custom  # rig, scene kept
    assert as_tuples(bagio.read_messages(tmp_path / "fixed")) == as_tuples(bagio.read_messages(bag))
    with Reader(tmp_path / "fixed") as r:
        assert r.message_count == n
    again = cli("maem-bag", "recover", bag, "--out", tmp_path / "fixed")
    assert "exists already" in one_line(again)
    cli("maem-bag", "recover", bag)  # in place, without metadata.yaml too
    assert bagio.bag_info(bag).damage == ""


def test_maem_bag_refuses_what_is_no_bag_in_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    assert "no metadata.yaml and no .mcap file" in one_line(cli("maem-bag", "info",
                                                                tmp_path / "empty"))
    (tmp_path / "text").mkdir()
    (tmp_path / "text" / "x.mcap").write_text("hello, not an MCAP file")
    assert "x.mcap is not an MCAP file" in one_line(cli("maem-bag", "recover",
                                                        tmp_path / "text"))
    assert "no such file" in one_line(cli("maem-bag", "info", tmp_path / "typo"))


@needs_demo
@pytest.mark.slow
def test_export_and_demo_read_a_cut_bag_without_metadata(tmp_path):
    bag = _cut_demo(tmp_path, 0.6, metadata=False)
    info = bagio.bag_info(bag)
    gt = info.counts[bagio.GT_TOPIC]
    assert 0 < gt < 30 and "metadata.yaml missing" in info.damage
    proc = cli("maem-export", bag, "--format", "csv", "--out", tmp_path / "csv", "--topic",
               bagio.GT_TOPIC)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(warnings) == 1 and warnings[0].startswith("maem-export: warning: ")
    assert f"{gt} messages" in proc.stdout


@needs_demo
def test_demo_reads_a_cut_bag(tmp_path, capsys):
    from maem_ros.tools.demo import demo_bag
    bag = _cut_demo(tmp_path, 0.6)
    d = demo_bag.load_bag(bag)
    assert 0 < len(d.stamps) < 30 and set(d.gt) <= set(d.stamps)
    assert d.rig_yaml and d.scene_config["seed"] == 0
    out = capsys.readouterr().out
    assert len([ln for ln in out.splitlines() if "warning" in ln]) == 1 and "cut short" in out
    assert demo_bag.ensure_bag(bag, frames=2) == bag


def test_cut_file_is_read_in_log_time_order_across_chunks(tmp_path):
    """Chunks whose times overlap (messages written out of order) are merged by log time in a
    cut file as in a whole one."""
    opts = bagio.WriteOptions(chunk_size=1e-4)  # every message its own chunk
    stamps = [5, 1, 7, 3, 9, 2, 8, 4, 6, 10]
    with bagio.BagWriter(tmp_path / "bag", options=opts, durable=False) as w:
        for s in stamps:
            w.write("/t", bagio.string_msg(f"m{s}"), s * 1000)
    whole = as_tuples(bagio.read_messages(tmp_path / "bag"))
    assert [t for _, t, _ in whole] == sorted(s * 1000 for s in stamps)
    mcap_file = tmp_path / "bag" / "bag.mcap"
    ends = [end for end, _ in record_faults.chunk_contents(mcap_file)]
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[:ends[-1] + 3])  # summary gone: read record by record
    cut = as_tuples(bagio.read_messages(tmp_path / "bag", start_ns=2000, stop_ns=9000))
    assert not bagio.bag_info(tmp_path / "bag").files[0].complete
    assert cut == [m for m in whole if 2000 <= m[1] < 9000]
