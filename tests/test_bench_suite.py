"""experiments/bench_suite.py's arithmetic: per module, CPU (waited-for children included) and the wall time beyond
it add up from the per-test records, most CPU first, and a test that waited gets no negative wait. Nothing timed."""
from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_modules_sum_their_tests_cpu_and_waits():
    spec = importlib.util.spec_from_file_location("bench_suite", ROOT / "experiments" / "bench_suite.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    records = [{"test": "tests/a.py::t1", "wall": 10.0, "cpu": 2.0},
               {"test": "tests/a.py::t2", "wall": 1.0, "cpu": 1.0},
               {"test": "tests/b.py::t[x]", "wall": 4.0, "cpu": 4.5}]  # children's CPU can exceed the wall
    assert bench.by_module(records) == [("tests/b.py", 4.5, 4.0, 0.0), ("tests/a.py", 3.0, 11.0, 8.0)]
