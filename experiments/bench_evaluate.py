"""Benchmark of the evaluate stage: is it bound by the model forward, not by image decoding?

For a real-size model graph (SegFormer-B0 widths, random weights: the cost of a forward does not depend
on the weights) it prints images/s of the evaluate stage (`evaluate.num_workers` = 0 and N decoding
processes) beside images/s of the bare model forward on the same images already in memory, and their
ratio (target: >= 0.9 with workers at batch 4); the share of evaluate time spent in metric accumulation;
and peak RSS for a small vs a large dataset (must stay flat: evaluate streams).

    python experiments/bench_evaluate.py [--groups 24] [--width 512 --height 256] [--workers 2] [--batch 4]
    python experiments/bench_evaluate.py --memory 50 500 --width 128 --height 64 --model tiny_segformer
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CONDITIONS = ("Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY")
# SegFormer-B0 (MiT-b0 encoder, 256-wide decoder): the smallest of the paper's models, so the one where
# decoding is the largest share of the time
B0 = ("{depths:[2,2,2,2],hidden_sizes:[32,64,160,256],num_attention_heads:[1,2,5,8],mlp_ratios:[4,4,4,4],"
      "decoder_hidden_size:256}")


def make_release_dataset(root: Path, n: int, width: int, height: int) -> None:
    """n groups x 3 conditions in the released layout, rendered by the synthetic backend."""
    from pairedgta.conditions import Condition
    from pairedgta.datasets.base import save_png_atomic
    from pairedgta.render.synthetic import SyntheticRenderer
    from pairedgta.scene import Location, SceneDescriptor

    r = SyntheticRenderer(width=width, height=height)
    conds = [Condition("Day-EXTRASUNNY", "Day", "EXTRASUNNY"),
             Condition("Day-RAIN", "Day", "RAIN", cloud_cover=0.9, rain_mm_h=25.0, visibility_m=350.0, wetness=1.0),
             Condition("Night-EXTRASUNNY", "Night", "EXTRASUNNY", clock_hour=0, sun_elevation_deg=-30)]
    for k in range(n):
        d = SceneDescriptor(scene_id=str(k), seed=k, location=Location(0, 0))
        for c in conds:
            (root / c.time).mkdir(parents=True, exist_ok=True)
            save_png_atomic(r.render(d, c).image, root / c.time / f"{k}_{c.time}_{c.weather}.png")


# one measurement per process, so peak RSS and thread pools are not shared between runs
CHILD = r"""
import json, resource, sys, time
import numpy as np
from hydra import compose, initialize_config_dir
import pairedgta.stages.evaluate as ev
from pairedgta.evaluation import tables
from pairedgta.models.base import Segmenter
from pairedgta.app import run
from pairedgta.configs import CONFIG_DIR

root, cache, model, workers, batch, arch = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
# the forward is timed only inside evaluate's count_groups (the pseudolabel stage runs forwards of its own,
# which once made the "forward share" exceed 100 %); the writing of the tables is timed on its own
timers = {"forward": 0.0, "evaluate": 0.0, "write": 0.0}
inside = [False]
predict = Segmenter.predict
def timed(self, images):
    t = time.perf_counter(); out = predict(self, images)
    if inside[0]:
        timers["forward"] += time.perf_counter() - t
    return out
Segmenter.predict = timed
count_groups = ev.count_groups
def wrapped(*a, **k):
    inside[0] = True
    t = time.perf_counter()
    try:
        return count_groups(*a, **k)
    finally:
        timers["evaluate"] += time.perf_counter() - t; inside[0] = False
ev.count_groups = wrapped
write_outputs = tables.write_outputs
def written(*a, **k):
    t = time.perf_counter(); out = write_outputs(*a, **k); timers["write"] += time.perf_counter() - t; return out
tables.write_outputs = written
overrides = ["dataset=paired_gta", f"dataset.root={root}", f"cache_dir={cache}", "stages=[pseudolabel,evaluate]",
             "tracking.enabled=false", f"model={model}", f"reference_model={model}", f"evaluate.num_workers={workers}",
             f"evaluate.batch_size={batch}", "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]",
             "metric.bootstrap.resamples=100"] + ([f"model.arch={arch}"] if arch != "-" else [])
with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
    cfg = compose("config", overrides=overrides)
summary = run(cfg)
timers["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
# the bare forward on the same images, decoded beforehand
from omegaconf import OmegaConf
from pairedgta.datasets import open_dataset, load_image
from pairedgta.conditions import build_condition_grid
from pairedgta.models import build_segmenter
c = OmegaConf.to_container(cfg, resolve=True)
ds = open_dataset(c["dataset"], build_condition_grid(c["conditions"]))
images = [load_image(g.images[k]) for g in ds.groups for k in sorted(g.images)]
seg = build_segmenter(c["model"], device="cpu")
t = time.perf_counter()
for s in range(0, len(images), batch):
    predict(seg, np.stack(images[s:s + batch]))
timers["bare"] = time.perf_counter() - t
timers["images"] = len(images)
print(json.dumps(timers))
"""


def measure(root: Path, cache: Path, model: str, workers: int, batch: int, arch: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(root), str(cache), model, str(workers), str(batch), arch],
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--groups", type=int, default=24)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--model", default="tiny_segformer")
    ap.add_argument("--arch", default=B0, help="model.arch override (default: SegFormer-B0 widths); - = the model's own")
    ap.add_argument("--memory", type=int, nargs="*", default=[], help="also peak RSS at these dataset sizes")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        make_release_dataset(root, args.groups, args.width, args.height)
        print(f"evaluate, {args.model} {'SegFormer-B0 widths' if args.arch == B0 else 'arch=' + args.arch}, {args.width}x{args.height}, {args.groups} groups x 3 conditions, "
              f"batch {args.batch}")
        # forward share: of count_groups' time, the model's forward; decode + counting: the rest of it;
        # writing: tables.write_outputs (every file of the entry: tables, bootstrap, group counts, label maps),
        # after count_groups, relative to it
        print(f"{'workers':>7} {'eval img/s':>10} {'bare img/s':>10} {'ratio':>6} {'forward share':>13} "
              f"{'decode+count':>12} {'writing':>8}")
        for workers in sorted({0, args.workers}):
            t = measure(root, Path(tmp) / f"cache{workers}", args.model, workers, args.batch, args.arch)
            n = t["images"]
            ev_ips, bare_ips = n / t["evaluate"], n / t["bare"]
            other = max(t["evaluate"] - t["forward"], 0.0)
            print(f"{workers:>7} {ev_ips:>10.2f} {bare_ips:>10.2f} {ev_ips / bare_ips:>6.2f} "
                  f"{t['forward'] / t['evaluate']:>13.1%} {other / t['evaluate']:>12.1%} {t['write'] / t['evaluate']:>8.1%}")
        rss = []
        for n in args.memory:
            r = Path(tmp) / f"mem{n}"
            make_release_dataset(r, n, args.width, args.height)
            rss.append((n, measure(r, Path(tmp) / f"cmem{n}", args.model, 0, args.batch, args.arch)["peak_rss_mb"]))
        for n, mb in rss:
            print(f"peak RSS with {n} groups: {mb:.0f} MB")
        if len(rss) >= 2:
            print(f"peak RSS ratio {rss[-1][0]} vs {rss[0][0]} groups: {rss[-1][1] / rss[0][1]:.3f} (flat = 1.0)")


if __name__ == "__main__":
    main()
