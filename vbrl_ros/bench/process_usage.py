"""CPU time and memory of a process and its children, sampled from Linux's /proc (no dependency).

``vbrl bench --node`` watches the node this way: its verification child counts
too. CPU is user + system time, summed over the process tree; RSS is sampled, so
a peak between two samples can be missed (the tree's own high-water marks are
read too, and the larger figure is kept).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

_TICKS = os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class Usage:
    cpu_s: float  # user + system seconds of the tree between start and stop
    wall_s: float
    peak_rss_mb: float
    first_rss_mb: float  # at the first sample, and at the last: is memory flat?
    last_rss_mb: float

    @property
    def cpu_percent(self) -> float:
        """Mean CPU over the window, in % of one core."""
        return 100.0 * self.cpu_s / self.wall_s if self.wall_s > 0 else float("nan")


def tree(pid: int) -> list[int]:
    """``pid`` and its descendants alive now."""
    out, todo = [], [pid]
    while todo:
        current = todo.pop()
        out.append(current)
        try:
            for task in Path(f"/proc/{current}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def _cpu_and_memory(pid: int) -> tuple[float, float, float]:
    """(cpu seconds, rss MB, high-water rss MB) of one process; zeros once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0, 0.0, 0.0
    kb = {line.split(":")[0]: float(line.split()[1]) for line in status.splitlines()
          if line.startswith(("VmRSS", "VmHWM"))}
    # fields after the name: state is [0], utime [11], stime [12] (stat(5) numbers 14 and 15)
    return (int(fields[11]) + int(fields[12])) / _TICKS, kb.get("VmRSS", 0.0) / 1024, kb.get("VmHWM", 0.0) / 1024


class ProcessSampler:
    """Samples a process tree every ``period`` s in a thread between :meth:`start` and :meth:`stop`."""

    def __init__(self, pid: int, period: float = 0.25) -> None:
        self.pid, self.period = pid, period
        self._cpu: dict[int, float] = {}  # latest cpu seconds per pid (children that ended keep theirs)
        self._rss: list[float] = []
        self._peaks: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> ProcessSampler:
        self._start_cpu = self._sample()
        self._start = time.monotonic()
        self._thread.start()
        return self

    def _sample(self) -> float:
        total_rss = 0.0
        for pid in tree(self.pid):
            cpu, rss, peak = _cpu_and_memory(pid)
            if cpu:
                self._cpu[pid] = cpu
            total_rss += rss
            self._peaks[pid] = max(self._peaks.get(pid, 0.0), peak)
        self._rss.append(total_rss)
        return sum(self._cpu.values())

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._sample()

    def stop(self) -> Usage:
        self._stop.set()
        self._thread.join()
        cpu = self._sample() - self._start_cpu
        wall = time.monotonic() - self._start
        peak = max(max(self._rss), max(self._peaks.values(), default=0.0))
        return Usage(cpu, wall, peak, self._rss[0], self._rss[-1])
