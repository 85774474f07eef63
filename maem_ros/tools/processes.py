"""Child processes of the graph tools (maem-demo, tools/bench/latency.py): start with a log file each,
watch, stop with SIGINT and collect exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from maem_ros.ros.cli import SHUTDOWN_STALLED, STALLED_WITH_GIL

#: node kind -> module run with ``python -m`` (works without installing the console scripts)
NODE_MODULES = {
    "frontend": "maem_ros.ros.frontend_node",
    "association": "maem_ros.ros.association_node",
    "triangulation": "maem_ros.ros.triangulation_node",
    "player": "maem_ros.ros.player_node",
    "recorder": "maem_ros.ros.recorder_node",
}


def module_command(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


def node_command(kind: str, params_file: str | Path, namespace: str | None = None) -> list[str]:
    """argv running one node with a params file (``python -m``, works without installing)."""
    cmd = module_command(NODE_MODULES[kind], "--ros-args", "--params-file", str(params_file))
    if namespace:
        cmd += ["-r", f"__ns:={namespace}"]
    return cmd


def kill_with_stacks(p: subprocess.Popen) -> None:
    """SIGUSR1 first (our commands dump their Python stacks into their log, see
    ros/cli.stop_on_signals), then SIGKILL."""
    if hasattr(signal, "SIGUSR1"):
        p.send_signal(signal.SIGUSR1)
        try:
            p.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            pass
    if p.poll() is None:
        p.kill()
        p.wait(timeout=5)


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen
    log: Path

    def tail(self, chars: int = 1500) -> str:
        try:
            return self.log.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def cpu_seconds(self) -> float:
        """user + system CPU seconds so far (Linux /proc), NaN when the process is gone."""
        try:
            parts = Path(f"/proc/{self.popen.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class ProcessGroup:
    """Child processes with logs in ``log_dir``; ``stop`` sends SIGINT and collects exit codes."""

    log_dir: Path
    env: dict[str, str]
    procs: dict[str, Proc] = field(default_factory=dict)

    def start(self, name: str, cmd: Sequence[str]) -> Proc:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        with open(log_path, "wb") as fh:
            popen = subprocess.Popen(
                list(cmd), stdout=fh, stderr=subprocess.STDOUT, env=self.env, stdin=subprocess.DEVNULL
            )
        self.procs[name] = Proc(name, popen, log_path)
        return self.procs[name]

    def dead(self, names: Sequence[str] | None = None) -> dict[str, int]:
        """{name: exit code} of the processes (of ``names``) that have exited."""
        return {
            n: p.popen.returncode
            for n, p in self.procs.items()
            if (names is None or n in names) and p.popen.poll() is not None
        }

    def stop(self, names: Sequence[str] | None = None, timeout_s: float = 10.0) -> dict[str, int | None]:
        """SIGINT ``names`` (default all) still running, wait up to ``timeout_s``; kill leftovers.
        Exit codes, None = had to be killed."""
        names = list(self.procs) if names is None else names
        for n in names:
            if self.procs[n].popen.poll() is None:
                self.procs[n].popen.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        codes: dict[str, int | None] = {}
        for n in names:
            p = self.procs[n].popen
            try:
                codes[n] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                kill_with_stacks(p)
                codes[n] = None
        return codes

    def forced_exits(self) -> list[str]:
        """Names of the processes whose shutdown watchdog ended them (see ros/cli.py: exit code
        0, or 1 from its backstop when the stalled teardown held the GIL)."""
        return [
            p.name
            for p in self.procs.values()
            if any(m in p.tail(100_000) for m in (SHUTDOWN_STALLED, STALLED_WITH_GIL))
        ]

    def shutdown(self) -> None:
        """SIGINT whatever still runs (recorder last, so it keeps what it received), then kill."""
        running = [n for n, p in self.procs.items() if p.popen.poll() is None]
        if running:
            # 15 s: ten nodes leaving DDS at once (shared-memory segments unmapped) can take
            # several seconds on a busy small machine; a kill there would be a false failure
            self.stop([n for n in running if n != "recorder"], timeout_s=15.0)
            if "recorder" in running:
                self.stop(["recorder"], timeout_s=10.0)

    def logs(self, tail: int = 2000, names: Sequence[str] | None = None) -> str:
        """The last ``tail`` characters of every log (of ``names``), one section per process."""
        return "\n".join(
            f"--- {p.name} ---\n{p.tail(tail)}"
            for p in self.procs.values()
            if (names is None or p.name in names) and p.log.exists()
        )
