"""Time and peak memory of a command, summed over every process it starts, and benchmark result files.

Memory is the proportional set size (PSS, /proc/PID/smaps_rollup): a page shared by k processes
counts 1/k in each, so the sum over a process tree is the memory the tree really holds (RSS would
count a page a forked worker shares with its parent twice).  The tree (the command and all its
descendants, re-listed at every sample, so workers started later are seen) is sampled every
`interval_s`, or less often where one sample costs more than SAMPLER_SHARE of that wait (reading the
smaps of a process of several GB walks its page tables: at 0.1 s the sampler took a third of a core
from the job it measured on a 2-core machine); the peak is the largest sum seen.  A spike shorter
than the interval can be missed, so each process's own high-water mark (VmHWM, kept by the kernel,
exact) is read too: `hwm_sum_gb`, their sum over every process seen, bounds the tree's peak from
above (a page shared by two processes counts twice) and equals it for one process.

    python benchmarks/measure.py [--interval 0.1] [--json OUT.json] -- relief diagnose S.toml -o OUT

prints one line `wall_s=... peak_pss_gb=... peak_processes=...` and, with --json, writes it as JSON.

`write_result(name, figures, command)` writes `benchmarks/results/NAME.json` (the command, the
machine, the figures, the time of the run): every benchmark keeps its last figures there, so the
next change is compared with numbers.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def _children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/children") as f:
                out.extend(int(c) for c in f.read().split())
        except OSError:
            pass
    return out


def process_tree(pid: int) -> list[int]:
    """`pid` and every live descendant."""
    seen, todo = [], [pid]
    while todo:
        p = todo.pop()
        seen.append(p)
        todo.extend(_children(p))
    return seen


def _proc_kb(path: str, field: str) -> int:
    """The `field:` line of a /proc file in bytes (its value is in kB; 0 when the process is gone)."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def pss_bytes(pid: int) -> int:
    """Proportional set size of one process (0 when it is gone or unreadable)."""
    return _proc_kb(f"/proc/{pid}/smaps_rollup", "Pss:")


def hwm_bytes(pid: int) -> int:
    """The process's resident high-water mark (VmHWM: the largest RSS it has had; 0 when gone)."""
    return _proc_kb(f"/proc/{pid}/status", "VmHWM:")


def tree_pss_bytes(pid: int) -> tuple[int, int]:
    """(PSS summed over `pid` and its descendants, how many processes)."""
    pids = process_tree(pid)
    return sum(pss_bytes(p) for p in pids), len(pids)


@dataclass
class Measure:
    """What a measured run cost."""

    wall_s: float
    peak_pss_gb: float
    peak_processes: int
    returncode: int
    hwm_sum_gb: float = 0.0
    sampler_cpu_s: float = 0.0

    def line(self) -> str:
        return (f"wall_s={self.wall_s:.1f} peak_pss_gb={self.peak_pss_gb:.2f} hwm_sum_gb={self.hwm_sum_gb:.2f} "
                f"peak_processes={self.peak_processes} rc={self.returncode}")


SAMPLER_SHARE = 0.02     # the most of one core the sampler may take from the job it measures


class PeakSampler:
    """Samples the PSS of a process tree on a thread until stopped: `peak_bytes` (the largest sum seen),
    `peak_processes`, `hwm_bytes` (the sum of each process's VmHWM, an upper bound) and `cpu_s` (what
    the sampling itself cost).  The wait between samples is `interval_s`, longer where a sample costs
    more than SAMPLER_SHARE of it."""

    def __init__(self, pid: int, interval_s: float = 0.1):
        self.pid, self.interval_s = pid, interval_s
        self.peak_bytes = 0
        self.peak_processes = 0
        self.cpu_s = 0.0
        self._hwm: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @property
    def hwm_bytes(self) -> int:
        return sum(self._hwm.values())

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.thread_time()
            pids = process_tree(self.pid)
            b = sum(pss_bytes(p) for p in pids)
            for p in pids:
                self._hwm[p] = max(self._hwm.get(p, 0), hwm_bytes(p))
            if b > self.peak_bytes:
                self.peak_bytes = b
            self.peak_processes = max(self.peak_processes, len(pids))
            cost = time.thread_time() - t0
            self.cpu_s += cost
            self._stop.wait(max(self.interval_s, cost / SAMPLER_SHARE))

    def __enter__(self) -> "PeakSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def measure_command(cmd: list[str], interval_s: float = 0.1, **popen) -> Measure:
    """Run `cmd`, sampling its process tree's PSS; the wall time and the peak."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, **popen)
    with PeakSampler(proc.pid, interval_s) as s:
        rc = proc.wait()
    return Measure(time.perf_counter() - t0, s.peak_bytes / 1e9, s.peak_processes, rc, s.hwm_bytes / 1e9, s.cpu_s)


def machine() -> dict:
    """The machine a figure was measured on."""
    mem_gb = None
    try:
        with open("/proc/meminfo") as f:
            mem_gb = round(int(f.readline().split()[1]) / 1e6, 1)
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "memory_gb": mem_gb, "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(), "system": platform.platform(terse=True)}


def write_result(name: str, figures: dict, command: str, results_dir: Path = RESULTS_DIR) -> Path:
    """Write `results_dir/NAME.json`: {"benchmark", "command", "machine", "when", "figures"} (atomic)."""
    results_dir.mkdir(parents=True, exist_ok=True)
    path = results_dir / f"{name}.json"
    doc = {"benchmark": name, "command": command, "machine": machine(),
           "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "figures": figures}
    tmp = path.with_suffix(".json.part")
    tmp.write_text(json.dumps(doc, indent=1, default=float) + "\n")
    os.replace(tmp, path)
    return path


class _LastJsonLine:
    """A stdout that passes everything through and remembers the last line that is a JSON object."""

    def __init__(self, stream):
        self.stream, self.last, self._buf = stream, None, ""

    def write(self, text: str) -> int:
        self._buf += text
        *lines, self._buf = self._buf.split("\n")
        for line in lines:
            if line.startswith("{"):
                try:
                    self.last = json.loads(line)
                except ValueError:
                    pass
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def __getattr__(self, name):
        return getattr(self.stream, name)


def bench(name: str, main, argv: list[str] | None = None) -> int:
    """Run a benchmark's `main(argv)` sampling this process tree's PSS, then write
    `results/NAME.json` with the figures of its last JSON line, its wall time and peak memory."""
    argv = list(sys.argv[1:] if argv is None else argv)
    out = _LastJsonLine(sys.stdout)
    t0 = time.perf_counter()
    old = sys.stdout
    sys.stdout = out
    try:
        with PeakSampler(os.getpid(), 0.1) as s:
            rc = main(argv)
    finally:
        sys.stdout = old
    figures = {"wall_s": round(time.perf_counter() - t0, 2), "peak_pss_gb": round(s.peak_bytes / 1e9, 3),
               "hwm_sum_gb": round(s.hwm_bytes / 1e9, 3), "peak_processes": s.peak_processes,
               "sampler_cpu_s": round(s.cpu_s, 1), "results": out.last}
    path = write_result(name, figures, " ".join(["benchmarks/" + name + ".py", *argv]))
    print(f"{name}: wall {figures['wall_s']} s, peak {figures['peak_pss_gb']} GB (PSS, every process); {path}")
    return rc if isinstance(rc, int) else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interval", type=float, default=0.1, help="sampling interval, s (default 0.1)")
    ap.add_argument("--json", help="write the figures as JSON here")
    ap.add_argument("cmd", nargs=argparse.REMAINDER, help="the command, after --")
    a = ap.parse_args(argv)
    cmd = a.cmd[1:] if a.cmd[:1] == ["--"] else a.cmd
    if not cmd:
        ap.error("no command given")
    m = measure_command(cmd, a.interval)
    print(m.line(), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"command": cmd, **asdict(m)}, indent=1) + "\n")
    return m.returncode


if __name__ == "__main__":
    sys.exit(main())
