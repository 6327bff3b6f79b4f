"""What checking a cache hit costs: a generate-sized entry (scenes x 9 conditions x image + label +
instance PNGs), verified against its manifest (size and sha256 of every file) with the hash memo
(stat + memo lookup, what a hit does) and without it (every file read and hashed again), next to
building the manifest once. Prints per-file times and the ratio.

    python experiments/bench_cache.py --scenes 100 --mb 1.5
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pairedgta.cache import StageCache, entry_problem  # noqa: E402
from pairedgta.filehash import HashMemo, MEMO_NAME  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--mb", type=float, default=1.5, help="size of an image file (labels: a tenth)")
    ap.add_argument("--dir", type=Path, default=None, help="where to build (default: a temp dir)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        cache = StageCache(tmp)
        image, label = int(args.mb * 2**20), int(args.mb * 2**20 / 10)
        t0 = time.perf_counter()
        with cache.build("generate", "0" * 16, {}) as out:
            for k in range(args.scenes):
                d = out / "scenes" / f"{k:05d}"
                d.mkdir(parents=True)
                for c in range(9):
                    (d / f"c{c}.png").write_bytes(os.urandom(image))
                    (d / f"c{c}_labels.png").write_bytes(os.urandom(label))
                    (d / f"c{c}_instances.png").write_bytes(os.urandom(label))
            t_write = time.perf_counter() - t0
        t_build = time.perf_counter() - t0 - t_write
        entry = cache.path("generate", "0" * 16)
        n = args.scenes * 27
        total_mb = args.scenes * 9 * (image + 2 * label) / 2**20
        os.sync()
        t0 = time.perf_counter()
        assert entry_problem(entry, HashMemo(Path(tmp) / MEMO_NAME)) is None
        memo_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        assert entry_problem(entry, HashMemo(None)) is None  # no memo: every file read again
        full_s = time.perf_counter() - t0
        print(f"entry: {n} files, {total_mb:.0f} MB")
        print(f"write files {t_write:.2f} s; manifest (hash every file) at build {t_build:.2f} s")
        print(f"hit check with memo:    {memo_s:.3f} s ({memo_s / n * 1e6:.0f} us/file)")
        print(f"hit check without memo: {full_s:.3f} s ({full_s / n * 1e6:.0f} us/file, {total_mb / full_s:.0f} MB/s)")
        print(f"ratio without/with memo: {full_s / memo_s:.0f}x")


if __name__ == "__main__":
    main()
