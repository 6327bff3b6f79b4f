"""What a cached rerun of the main job costs, and how much of it is the MLflow record: the same command
(`python -m pairedgta cache_dir=...`) with every stage a cache hit, timed as a user would (a fresh
interpreter each time), with the record logged by the tracking child (the default), in the run's own
process (`tracking.background=false`), and with no record (`tracking.enabled=false`). Prints the median
of each and the ratios. The first run fills the cache when it is empty (about 3 minutes on 2 cores).

    python experiments/bench_rerun.py --cache-dir /tmp/pgta-cache --repeats 3
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MODES = {
    "background record (default)": [],
    "record in the run's process": ["tracking.background=false"],
    "no record": ["tracking.enabled=false"],
}


def timed(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pairedgta", *args], cwd=cwd, capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"bench_rerun: the run failed ({proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}")
    return took


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache-dir", type=Path, default=None, help="a cache to reuse (default: a new temp folder)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="pgta-bench-rerun-") as tmp:
        cache = (args.cache_dir or Path(tmp) / "cache").resolve()
        base = [f"cache_dir={cache}", f"tracking.uri=sqlite:///{Path(tmp) / 'mlflow.db'}", f"hydra.run.dir={tmp}/run"]
        first = timed(base, Path(tmp))  # fills the cache if needed, and creates the store
        print(f"first run (fills an empty cache, creates the store): {first:.1f} s")
        medians = {}
        for mode, extra in MODES.items():
            times = [timed(base + extra, Path(tmp)) for _ in range(args.repeats)]
            medians[mode] = statistics.median(times)
            print(f"{mode:30s} median {medians[mode]:.2f} s  ({', '.join(f'{t:.2f}' for t in times)})")
        none = medians["no record"]
        for mode, m in medians.items():
            print(f"{mode:30s} {m / none:.2f}x the run without a record")


if __name__ == "__main__":
    main()
