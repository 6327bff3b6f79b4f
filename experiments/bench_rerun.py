"""What a cached rerun of the main job costs, and how much of it is the MLflow record: the same command
(`python -m pairedgta cache_dir=...`) with every stage a cache hit, timed as a user would (a fresh
interpreter each time), with the record logged by the tracking child (the default), in the run's own
process (`tracking.background=false`), and with no record (`tracking.enabled=false`). Prints the median
of each and the ratios, and for the default what the tracking child reported (its MLflow import, its store
calls, and how long the run waited for it once its own work was done). The first run fills the cache when
it is empty (about 2-3 minutes on 2 cores).

    python experiments/bench_rerun.py --cache-dir /tmp/pgta-cache --repeats 3
"""
from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BACKGROUND = "background record (default)"
MODES = {
    BACKGROUND: ["hydra.verbose=pairedgta.tracking"],  # the child's timings, one DEBUG line
    "record in the run's process": ["tracking.background=false"],
    "no record": ["tracking.enabled=false"],
}


CHILD = re.compile(r"tracking child: MLflow import ([\d.]+) s, store calls ([\d.]+) s, waited for ([\d.]+) s")


def timed(args: list[str], cwd: Path, child: list[tuple[float, ...]] | None = None) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pairedgta", *args], cwd=cwd, capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"bench_rerun: the run failed ({proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}")
    found = CHILD.search(proc.stdout + proc.stderr)
    if child is not None and found:
        child.append(tuple(float(x) for x in found.groups()))
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
        child: list[tuple[float, ...]] = []
        for mode, extra in MODES.items():
            times = [timed(base + extra, Path(tmp), child if mode == BACKGROUND else None) for _ in range(args.repeats)]
            medians[mode] = statistics.median(times)
            print(f"{mode:30s} median {medians[mode]:.2f} s  ({', '.join(f'{t:.2f}' for t in times)})")
        if child:
            imp, store, wait = (statistics.median(c[i] for c in child) for i in range(3))
            print(f"tracking child (medians): MLflow import {imp:.2f} s, store calls {store:.2f} s; the run waited "
                  f"{wait:.2f} s for it after its own work")
        none = medians["no record"]
        for mode, m in medians.items():
            print(f"{mode:30s} {m / none:.2f}x the run without a record")


if __name__ == "__main__":
    main()
