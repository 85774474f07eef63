"""The recorder under faults, with real processes: ``maem-play bags/demo --loop`` feeds
``maem-record``, which is SIGKILLed at random moments (then ``maem-bag info`` / ``recover``), runs
into a file size limit (EFBIG) or a full tmpfs (ENOSPC), or splits its files. Every message read
back is byte-identical to one the player published; the longer randomised runs are
``maem-record-faults`` (doc/recording.md)."""
from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from maem_ros import bagio
from maem_ros.tools.bags import record_faults

REPO = Path(__file__).resolve().parents[1]
DEMO_BAG = REPO / "bags" / "demo"
BIN = Path(sys.executable).parent

pytestmark = [pytest.mark.ros,
              pytest.mark.skipif(not (DEMO_BAG / "metadata.yaml").is_file(),
                                 reason="no committed bags/demo in this checkout")]


@pytest.fixture(scope="module")
def source() -> record_faults.Source:
    return record_faults.Source.load(DEMO_BAG)


@pytest.fixture(scope="module")
def feed(tmp_path_factory):
    """maem-play bags/demo --loop --reliable-images for the whole module."""
    with record_faults.Feed(DEMO_BAG, tmp_path_factory.mktemp("feed") / "play.log") as f:
        yield f


@pytest.mark.parametrize("seed,low_traffic", [(1, False), (2, True), (3, False)])
def test_sigkill_at_a_random_moment_then_recover(tmp_path, source, feed, seed, low_traffic):
    """Everything logged more than 1 s before the kill is recovered: the newest recovered
    message is at most 1 s older than the kill, and the recorder writes what it receives in
    order, in whole chunks, so nothing before it is missing (a message DDS never delivered
    under load is a hole record_faults counts apart)."""
    out = tmp_path / "rec"
    r = record_faults.kill_run(out, source, random.Random(seed), low_traffic, max_delay_s=3.0)
    assert r.recover_rc == 0, r.recover_text
    assert r.cut_seen  # maem-bag info said the last file was cut short
    assert r.recovered > 0 and r.garbled == 0, r  # (holes: DDS did not deliver, see ok)
    assert r.window_s <= 1.0, r
    assert "recovered" in r.recover_text and "rewritten up to its last whole chunk" in \
        r.recover_text
    info = bagio.bag_info(out)  # after recover: a sound bag, metadata.yaml rebuilt
    assert info.damage == "" and all(fs.complete for fs in info.files)
    assert bagio.metadata.load(out).message_count == r.recovered


def test_file_size_limit_efbig(tmp_path, source, feed):
    (tmp_path / "d").mkdir()
    r = record_faults.disk_full_run(tmp_path / "d" / "bag", source, "fsize", 12.0)
    assert r.rc == 1 and r.ok, r
    assert str(tmp_path / "d" / "bag") in r.last_line and "File too large" in r.last_line


def test_full_tmpfs_enospc(tmp_path, source, feed):
    with record_faults.Tmpfs(tmp_path / "small", 16) as fs:
        if not fs.ok:
            pytest.skip(f"cannot mount a tmpfs here: {fs.why}")
        r = record_faults.disk_full_run(fs.path / "bag", source, "tmpfs", 16.0)
    for log in r.stalls:  # a stalled attempt was started again: where it stood (-rA shows it)
        print(f"stalled recorder attempt, log tail:\n{log}")
    assert r.rc == 1 and r.ok, r
    assert "No space left on device" in r.last_line


def test_a_recording_that_stops_growing_is_killed_with_its_stacks(tmp_path):
    """The full-disk runs' stall guard: a recorder whose files stop growing is asked for its
    Python stacks (SIGUSR1, faulthandler) and killed; an exiting one gives its exit code."""
    log = tmp_path / "stuck.log"
    code = ("import faulthandler, signal, time; "
            "faulthandler.register(signal.SIGUSR1, all_threads=True); time.sleep(120)")
    with open(log, "w") as f:
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=f, stderr=subprocess.STDOUT)
    assert record_faults.wait_exit_or_stall(proc, tmp_path / "bag", 60.0, 1.0) is None
    assert proc.poll() is not None
    assert "time.sleep" in log.read_text() or "<string>" in log.read_text(), log.read_text()
    done = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    assert record_faults.wait_exit_or_stall(done, tmp_path / "bag", 60.0, 30.0) == 3


def test_split_files_and_metadata_kept_current(tmp_path, source, feed):
    """--max-bag-duration 1: a new complete file every second of log time; metadata.yaml is
    there and lists what is on disk while recording; SIGINT (Ctrl-C) closes the last file.
    (Stopped once three files are listed, not after a fixed time: how long the recorder
    takes to discover the player depends on the machine's load.)"""
    out = tmp_path / "split"
    proc = subprocess.Popen([*record_faults.RECORD, str(out), "--all", "--max-bag-duration",
                             "1"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        if not record_faults.wait_data(out, proc, 1 << 20, 60.0):
            proc.kill()
            said = proc.communicate(timeout=10)[0]
            pytest.fail(f"nothing recorded in 60 s; feed exit code {feed.proc.poll()}, its log: "
                        f"{feed.log.read_text()[-1500:]!r}; the recorder said: {said[-1500:]!r}")
        time.sleep(2.0)
        meta = bagio.metadata.load(out)  # mid-recording
        assert meta.message_count > 0 and len(meta.files) >= 1
        deadline = time.monotonic() + 60.0
        while len(bagio.metadata.load(out).files) < 3 and time.monotonic() < deadline:
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        text, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, text
    info = bagio.bag_info(out)
    assert len(info.files) >= 3 and all(fs.complete for fs in info.files), info.files
    assert all((fs.end_ns - fs.start_ns) < 1e9 for fs in info.files)
    assert f"wrote {info.message_count} messages" in text and f"in {len(info.files)} file(s)" \
        in text
    c = source.check(bagio.read_messages(out, info=info))
    assert c.count == info.message_count and c.garbled == 0


def test_duration_stops_the_recorder(tmp_path):
    """--duration S: the recorder stops by itself after S seconds and closes a sound bag (here
    of a topic nobody publishes: nothing to wait for but the clock)."""
    out = tmp_path / "timed"
    t0 = time.monotonic()
    proc = subprocess.run([*record_faults.RECORD, str(out), "--topics", "/nobody/publishes",
                           "--duration", "2"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert time.monotonic() - t0 >= 2.0
    assert f"wrote 0 messages to {out}" in proc.stdout, proc.stdout
    assert bagio.bag_info(out).damage == ""


def test_bad_split_option_is_one_line(tmp_path):
    proc = subprocess.run([*record_faults.RECORD, str(tmp_path / "x"), "--all",
                           "--max-bag-size", "-5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "--max-bag-size: must be >= 0" in proc.stderr
    proc = subprocess.run([*record_faults.RECORD, str(tmp_path / "x"), "--all", "--ros-args",
                           "-p", "max_bag_duration:=-1.0"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "max_bag_duration" in proc.stderr, proc.stderr
    assert not (tmp_path / "x").exists()


def test_player_plays_a_cut_bag_with_one_warning(tmp_path):
    bag = tmp_path / "cut"
    bag.mkdir()
    (bag / "metadata.yaml").write_bytes((DEMO_BAG / "metadata.yaml").read_bytes())
    data = (DEMO_BAG / "demo.mcap").read_bytes()
    (bag / "demo.mcap").write_bytes(data[:len(data) // 2])
    n = bagio.bag_info(bag).message_count
    proc = subprocess.run([str(BIN / "maem-play"), str(bag), "--delay", "0", "--topics",
                           "/maem/gt_poses", "/camera_0/camera_info"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if "warning" in ln.lower()]
    assert len(warnings) == 1 and "cut short" in warnings[0] and f"{n:,} complete" in warnings[0]
    counts = bagio.bag_info(bag).counts
    played = counts["/maem/gt_poses"] + counts["/camera_0/camera_info"]
    assert f"published {played} messages" in proc.stderr + proc.stdout
