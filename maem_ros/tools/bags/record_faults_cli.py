"""maem-record-faults' command line: the runs of tools/bags/record_faults.py chosen by the
options, their results as one table (its module docstring says what each run checks)."""

from __future__ import annotations

import argparse
import random
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from maem_ros import bagio
from maem_ros.tools.bags import record_faults
from maem_ros.tools.bags.record_faults import (
    DiskResult,
    Feed,
    Source,
    Tmpfs,
    _default_bag,
    cut_bag,
    cut_run,
    disk_full_run,
    kill_run,
    long_run,
)

DOC = record_faults.__doc__ or ""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-record-faults",
        description=DOC.split("\n\n")[0],
        epilog=DOC.split("\n\n", 2)[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--bag", type=Path, default=None, help="bag the player loops (default bags/demo)")
    p.add_argument("--kills", type=int, default=20, help="SIGKILL runs (default 20)")
    p.add_argument("--cuts", type=int, default=100, help="cut offsets (default 100)")
    p.add_argument("--disk", action="store_true", help="full-disk runs (file size limit; tmpfs when root)")
    p.add_argument(
        "--long",
        type=float,
        default=0.0,
        metavar="MIN",
        help="a MIN-minute recording split every --split s (default off)",
    )
    p.add_argument("--split", type=float, default=60.0, metavar="S")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--work", type=Path, default=Path("out/record_faults"), help="scratch folder (emptied first)"
    )
    return p


def _table(rows: list[tuple[str, str, str]]) -> str:
    lines = ["| case | result | detail |", "|---|---|---|"]
    return "\n".join(lines + [f"| {a} | {b} | {c} |" for a, b, c in rows])


def run_all(a: argparse.Namespace, log=print) -> list[tuple[str, str, str]]:
    rng = random.Random(a.seed)
    bag = a.bag or _default_bag()
    source = Source.load(bag)
    rows = []
    if a.cuts:
        src = cut_bag(bag, a.work)
        size = bagio.bag_info(src).files[-1].size
        cuts = [
            cut_run(src, a.work / "cut", rng.randrange(8, size), drop_metadata=i % 2 == 1)
            for i in range(a.cuts)
        ]
        ok = sum(c.ok for c in cuts)
        rows.append(
            (
                f"cut at {a.cuts} random offsets",
                f"{ok}/{a.cuts} exact",
                f"{sum(c.got for c in cuts):,} messages read back, "
                f"{sum(c.garbled for c in cuts)} garbled, {sum(c.missing for c in cuts)} "
                f"missing, {sum(c.extra for c in cuts)} from cut chunks; "
                f"{sum(bool(c.refused) for c in cuts)} cuts left nothing complete (refused "
                f"in one line)",
            )
        )
        log(rows[-1])
    if a.kills or a.disk or a.long:
        with Feed(bag, a.work / "play.log") as feed:
            if a.kills:
                kills = [
                    kill_run(a.work / f"kill_{i}", source, rng, low_traffic=i % 2 == 1)
                    for i in range(a.kills)
                ]
                for r in kills:
                    log(
                        f"kill after {r.delay_s:.2f} s ({r.topics}): window {r.window_s:.3f} s, "
                        f"{r.recovered} recovered, garbled {r.garbled}, holes {r.holes}, "
                        f"rc {r.recover_rc}"
                    )
                w = sorted(r.window_s for r in kills)
                rows.append(
                    (
                        f"SIGKILL at {a.kills} random moments",
                        f"{sum(r.ok for r in kills)}/{a.kills} ok",
                        f"newest recovered message {w[0]:.2f}-{w[-1]:.2f} "
                        f"s before the kill (median {w[len(w) // 2]:.2f}); "
                        f"{sum(r.recovered for r in kills):,} messages, "
                        f"{sum(r.garbled for r in kills)} garbled, "
                        f"{sum(r.holes for r in kills)} holes in what DDS delivered; "
                        f"{sum(r.restarts for r in kills)} recorders restarted (no message "
                        f"in 30 s)",
                    )
                )
            if a.disk:
                rows += _disk_rows(a.work, source, log)
            if a.long:
                lr = long_run(a.work / "long", source, feed, a.long, a.split)
                rows.append(
                    (
                        f"{a.long:g} min split every {a.split:g} s",
                        f"{'ok' if lr.ok else 'FAILED'}: {lr.complete}/{lr.files} complete files",
                        f"{lr.written:,} written of {lr.received:,} received, "
                        f"garbled {lr.garbled}; {lr.holes} holes in what DDS delivered "
                        f"({lr.lost:,} counted lost by the recorder); "
                        f"file spans "
                        f"{min(lr.durations_s):.1f}-{max(lr.durations_s):.1f} s; player: "
                        f"{lr.published.split('] ')[-1]}",
                    )
                )
    return rows


def _disk_row(name: str, r: DiskResult) -> tuple[str, str, str]:
    stalled = f", {len(r.stalls)} stalled attempt(s) started again" if r.stalls else ""
    return (
        name,
        f"{'ok' if r.ok else 'FAILED'}: exit {r.rc}, "
        f"{r.readable:,} readable = said {r.said:,}, {r.holes} holes{stalled}",
        r.last_line,
    )


def _disk_rows(work: Path, source: Source, log) -> list[tuple[str, str, str]]:
    (work / "fsize").mkdir(parents=True)
    fsize = disk_full_run(work / "fsize" / "bag", source, "fsize", 24.0)
    rows = [_disk_row("file size limit 24 MB (EFBIG)", fsize)]
    log(rows[-1])
    with Tmpfs(work / "tmpfs", 32) as fs:
        if not fs.ok:
            rows.append(("tmpfs 32 MB (ENOSPC)", "skipped", fs.why))
        else:
            full = disk_full_run(fs.path / "bag", source, "tmpfs", 32.0)
            rows.append(_disk_row("tmpfs 32 MB (ENOSPC)", full))
    log(rows[-1])
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.work.exists():
        shutil.rmtree(a.work)
    a.work.mkdir(parents=True)
    t0 = time.monotonic()
    rows = run_all(a)
    print(_table(rows))
    print(f"({time.monotonic() - t0:.0f} s, seed {a.seed}, bag {a.bag or _default_bag()})")
    return 0 if all(not b.startswith(("FAILED", "0/")) for _, b, _ in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
