"""Where the test suite's time goes: per test module, the CPU its tests spent (the worker's own and that of the
child processes it waited for) and the wall time they took beyond it (waits on locks, servers, SLURM jobs); and for
the whole run, the wall time and the machine's busy core-seconds (/proc/stat before and after, so SLURM jobs and
servers that are no child of pytest count too). Issue 69 judges the suite against the main job by wall time on a
2-core machine: what a module spends in CPU is what it takes from the other worker, what it spends waiting is what
a shorter wait gives back.

    python experiments/bench_suite.py                         # README's test command (-n auto)
    python experiments/bench_suite.py -n0 tests/test_slurm.py  # one module on one core

Arguments go to pytest as they are. The per-test numbers come from this module loaded as a pytest plugin in each
worker (`-p bench_suite`); a killed child (kill -9) is never waited for and its CPU is not counted.
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

_LOG = "PAIREDGTA_BENCH_SUITE_LOG"
_started: dict[str, tuple[float, float]] = {}


def _cpu() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def pytest_runtest_logstart(nodeid, location):
    _started[nodeid] = (time.perf_counter(), _cpu())


def pytest_runtest_logfinish(nodeid, location):
    # (xdist's controller sees these hooks too, with none of the test's work: main() keeps the worker's record)
    if nodeid not in _started or not os.environ.get(_LOG):
        return
    wall0, cpu0 = _started.pop(nodeid)
    record = {"test": nodeid, "wall": time.perf_counter() - wall0, "cpu": _cpu() - cpu0}
    with open(Path(os.environ[_LOG]) / f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def by_module(records: list[dict]) -> list[tuple[str, float, float, float]]:
    """(module, CPU s, wall s, wall beyond CPU s) per test module, most CPU first."""
    cpu, wall = defaultdict(float), defaultdict(float)
    for r in records:
        module = r["test"].split("::")[0]
        cpu[module] += r["cpu"]
        wall[module] += r["wall"]
    rows = [(m, cpu[m], wall[m], max(wall[m] - cpu[m], 0.0)) for m in cpu]
    return sorted(rows, key=lambda row: -row[1])


def _busy_core_seconds() -> float | None:
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except OSError:
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle, iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str]) -> int:
    with tempfile.TemporaryDirectory(prefix="bench-suite-") as logs:
        env = {**os.environ, _LOG: logs,
               "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parent), os.environ.get("PYTHONPATH", "")])}
        busy0, start = _busy_core_seconds(), time.perf_counter()
        code = subprocess.call([sys.executable, "-m", "pytest", "-q", "-p", "bench_suite", *argv], env=env)
        wall, busy1 = time.perf_counter() - start, _busy_core_seconds()
        records = [json.loads(line) for f in Path(logs).glob("*.jsonl") for line in f.read_text().splitlines()]
    # a test logged twice (controller and worker) keeps the record with the CPU in it
    kept = {}
    for r in records:
        if r["test"] not in kept or r["cpu"] > kept[r["test"]]["cpu"]:
            kept[r["test"]] = r
    rows = by_module(list(kept.values()))
    print(f"\n{'module':<48} {'CPU s':>7} {'wall s':>7} {'waiting s':>9}")
    for module, cpu, w, waiting in rows[:25]:
        print(f"{module:<48} {cpu:7.1f} {w:7.1f} {waiting:9.1f}")
    total_cpu = sum(r[1] for r in rows)
    busy = f", the machine busy {busy1 - busy0:.0f} core-s" if busy0 is not None and busy1 is not None else ""
    print(f"{len(kept)} tests: {total_cpu:.0f} CPU-s in tests (waited-for children included), "
          f"{sum(r[3] for r in rows):.0f} s waiting; wall {wall:.1f} s{busy}")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
