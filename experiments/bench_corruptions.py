"""Seconds per image of each 2D corruption (conditions=corruptions, pairedgta/corruptions.py), per severity, on a
rendered-like image of the main job's size: which corruptions make a corruption set slow to generate.

    python experiments/bench_corruptions.py              # the 15 common corruptions, 512x256, severity 1 and 5
    python experiments/bench_corruptions.py --size 1024x512 --repeat 3 --subset all --severities 1 2 3 4 5
    python experiments/bench_corruptions.py --image outputs/cache/generate/<hash>/scenes/00000/Day-EXTRASUNNY.png

Prints one line per corruption and severity (the median of --repeat runs and every run's time), then the total per
image of the whole set: the generate stage adds that to each scene (timings.csv, `corruption_time`), in parallel over
scenes with generate.workers. CPU seconds are printed beside wall time, and the load average, because a shared
machine inflates wall time. Nothing is asserted: the times are the machine's.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pairedgta import corruptions  # noqa: E402


def test_image(width: int, height: int) -> np.ndarray:
    """A street-like image (sky, road, blocks, texture) when no rendered image is given: the filters' cost depends on
    the size, not much on the content."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:height, 0:width]
    img = np.empty((height, width, 3), np.float64)
    img[...] = (120, 160, 220)
    road = y > height * 0.55
    img[road] = (90, 90, 95)
    for k in range(8):
        x0 = int(k * width / 8)
        img[int(height * 0.25):int(height * 0.55), x0:x0 + width // 12] = rng.integers(40, 220, 3)
    img += rng.normal(0, 6, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="512x256", help="WxH of the synthetic test image (default: the main job's)")
    parser.add_argument("--image", type=Path, default=None, help="a rendered image instead of the synthetic one")
    parser.add_argument("--subset", default="common", choices=sorted(corruptions.SUBSETS))
    parser.add_argument("--severities", type=int, nargs="+", default=[1, 5])
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    if args.image:
        from pairedgta.datasets import load_image

        image = load_image(args.image)
    else:
        w, h = (int(v) for v in args.size.lower().split("x"))
        image = test_image(w, h)
    corruptions.library()  # its import (OpenCV, scikit-image) is not part of any corruption's time
    corruptions.corrupt(image, "brightness", 1, 0)  # warm-up: first calls load scikit-image's colour code
    print(f"image {image.shape[1]}x{image.shape[0]}, imagecorruptions {corruptions.library_version()}, "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'corruption':18} {'sev':>3} {'median s':>9} {'cpu s':>7}  runs (s)")
    per_image = 0.0
    slowest: list[tuple[float, str]] = []
    for name in corruptions.SUBSETS[args.subset]:
        for severity in args.severities:
            walls, cpus = [], []
            for r in range(args.repeat):
                c0, t0 = time.process_time(), time.perf_counter()
                corruptions.corrupt(image, name, severity, seed=r)
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            med = statistics.median(walls)
            per_image += med
            slowest.append((med, f"{name}-{severity}"))
            runs = " ".join(f"{w:.3f}" for w in walls)
            print(f"{name:18} {severity:3d} {med:9.3f} {statistics.median(cpus):7.3f}  {runs}")
    top = ", ".join(f"{n} {t:.2f} s" for t, n in sorted(slowest)[-3:][::-1])
    print(f"total per image over {len(corruptions.SUBSETS[args.subset])} corruptions x {len(args.severities)} "
          f"severities: {per_image:.2f} s; slowest: {top}")


if __name__ == "__main__":
    main()
