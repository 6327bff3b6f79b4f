"""Benchmark of the evaluate stage with the tiny model.

Prints images/s, the share of evaluate time spent in metric accumulation vs model forward (target:
metrics <= 5 %), and peak RSS for 50 vs 500 groups (must stay flat: evaluate streams).

    python experiments/bench_evaluate.py [--sizes 50 500] [--width 128 --height 64]
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make_release_dataset(root: Path, n: int, width: int, height: int) -> None:
    """n groups x 3 conditions in the released layout, rendered by the synthetic backend."""
    from pairedgta.conditions import Condition
    from pairedgta.datasets.base import save_png_atomic
    from pairedgta.render.synthetic import SyntheticRenderer
    from pairedgta.scene import Location, SceneDescriptor

    r = SyntheticRenderer(width=width, height=height)
    conds = [Condition("Day-EXTRASUNNY", "Day", "EXTRASUNNY"),
             Condition("Day-RAIN", "Day", "RAIN", cloud_cover=0.9, rain_intensity=0.7, wetness=1.0),
             Condition("Night-EXTRASUNNY", "Night", "EXTRASUNNY", clock_hour=0, sun_elevation_deg=-30)]
    for k in range(n):
        d = SceneDescriptor(scene_id=str(k), seed=k, location=Location(0, 0))
        for c in conds:
            (root / c.time).mkdir(parents=True, exist_ok=True)
            save_png_atomic(r.render(d, c).image, root / c.time / f"{k}_{c.time}_{c.weather}.png")


CHILD = r"""
import json, resource, sys, time
from hydra import compose, initialize_config_dir
import pairedgta.stages.evaluate as ev
from pairedgta.models.base import Segmenter
from pairedgta.app import run

timers = {"forward": 0.0, "io": 0.0}
def timed(fn, key):
    def wrapper(*a, **k):
        t = time.perf_counter(); out = fn(*a, **k); timers[key] += time.perf_counter() - t; return out
    return wrapper
Segmenter.predict = timed(Segmenter.predict, "forward")
ev.load_group_images = timed(ev.load_group_images, "io")
ev.load_label = timed(ev.load_label, "io")
compute = ev.compute
def wrapped(*a, **k):
    t = time.perf_counter(); out = compute(*a, **k); timers["evaluate"] = time.perf_counter() - t; return out
ev.compute = wrapped
root, cache, conf = sys.argv[1:4]
with initialize_config_dir(config_dir=conf, version_base="1.3"):
    cfg = compose("config", overrides=["dataset=paired_gta", f"dataset.root={root}", f"cache_dir={cache}",
        "stages=[pseudolabel,evaluate]", "tracking.enabled=false", "models=[tiny_segformer]",
        "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]", "metric.bootstrap.resamples=200"])
run(cfg)
timers["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(timers))
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[50, 500])
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=64)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            root = Path(tmp) / f"ds{n}"
            make_release_dataset(root, n, args.width, args.height)
            out = subprocess.run([sys.executable, "-c", CHILD, str(root), str(Path(tmp) / f"cache{n}"), str(ROOT / "pairedgta" / "conf")],
                                 capture_output=True, text=True, check=True)
            t = json.loads(out.stdout.strip().splitlines()[-1])
            images = n * 3
            metrics = t["evaluate"] - t["forward"] - t["io"]
            rows.append((n, images / t["evaluate"], 1000 * t["evaluate"] / images, t["forward"] / t["evaluate"],
                         metrics / t["evaluate"], metrics / t["forward"], t["peak_rss_mb"]))
    print(f"evaluate, tiny_segformer, {args.width}x{args.height}, 3 conditions per group")
    print(f"{'groups':>6} {'img/s':>7} {'ms/img':>7} {'forward':>8} {'metrics':>8} {'metrics/fwd':>11} {'peak RSS MB':>11}")
    for n, ips, ms, fwd, met, ratio, rss in rows:
        print(f"{n:>6} {ips:>7.1f} {ms:>7.2f} {fwd:>8.1%} {met:>8.1%} {ratio:>11.1%} {rss:>11.0f}")
    if len(rows) >= 2:
        print(f"peak RSS ratio {rows[-1][0]} vs {rows[0][0]} groups: {rows[-1][-1] / rows[0][-1]:.3f} (flat = 1.0)")


if __name__ == "__main__":
    main()
