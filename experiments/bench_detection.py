"""Benchmark of task=detection's evaluate stage: is it bound by the detector's forward, not by decoding, matching,
COCO AP or writing?

It renders a small dataset with the synthetic backend, pseudo-labels it with the reference detector, then times, on
the same images, the bare forward (the detector on images already decoded in memory, `Detector.detect`, nothing else)
and the evaluate stage's build for the same detector (decoding the PNGs, the forward, detection xi with its bootstrap,
pseudo-AP and COCO AP through pycocotools, the per-object table, the COCO results files and summary). Each stage run is
compared with the bare forwards just before and after it; the median of `--repeats` runs is printed as per-image
times and their ratio (target: >= 0.9 on the CPU).

    python experiments/bench_detection.py [--groups 8] [--width 512 --height 256] [--model tiny_fcos] [--repeats 3]

The default detector is `tiny_fcos` built at the zoo's widths (MobileNetV3 0.5, FPN 64, min_size 512; random
weights: the cost of the forward does not depend on them, and an untrained head sends the most boxes to the
matching and to pycocotools, the stage's worst case); `--zoo` keeps the named model's own config.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a checkout without the package installed

ZOO_WIDTHS = {"width": 0.5, "fpn_channels": 64, "min_size": 512, "max_size": 1024, "score_threshold": 0.3}


def overrides(cache: Path, groups: int, width: int, height: int, model: str, zoo: bool, threads: int) -> list[str]:
    args = [f"cache_dir={cache}", "+experiment=smoke_detection", f"generate.num_scenes={groups}",
            f"renderer.width={width}", f"renderer.height={height}", f"models=[{model}]", f"reference_model={model}",
            "tracking.enabled=false", f"threads={threads}", "metric.bootstrap.resamples=1000"]
    if not zoo:
        args += [f"+model_overrides.{model}.{k}={v}" for k, v in ZOO_WIDTHS.items()]
    return args


def measure(groups: int, width: int, height: int, model: str, zoo: bool, repeats: int, threads: int) -> dict[str, Any]:
    import torch
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import pairedgta.models as models
    from pairedgta.app import run
    from pairedgta.conditions import build_condition_grid
    from pairedgta.configs import CONFIG_DIR
    from pairedgta.datasets import load_group_images, open_dataset
    from pairedgta.models.runtime import reuse_freed_memory
    from pairedgta.stages import evaluate as evaluate_stage

    reuse_freed_memory()
    torch.set_num_threads(threads)
    with tempfile.TemporaryDirectory(prefix="pgta-bench-det-") as tmp:
        args = overrides(Path(tmp) / "cache", groups, width, height, model, zoo, threads)
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("config", overrides=args + ["stages=[generate,pseudolabel]"])
            again = compose("config", overrides=args + ["stages=[evaluate]", "force=[evaluate]"])
        root = run(cfg)["dataset"]
        c = OmegaConf.to_container(again, resolve=True)
        ds = open_dataset(c["dataset"], build_condition_grid(c["conditions"]), root=root)
        images = [list(load_group_images(g, ds.conditions).values()) for g in ds.groups]
        n = sum(len(g) for g in images)
        model_cfg = models.with_defaults({**models.model_config(model), **(c["model_overrides"].get(model) or {})})
        detector = models.build_model(model_cfg)
        build = models.build_model
        models.build_model = lambda cfg, device=None, **kw: detector  # the stage runs the detector just timed

        import numpy as np

        def bare() -> float:
            start = time.perf_counter()
            for g in images:
                detector.detect(np.stack(g))
            return time.perf_counter() - start

        stage_times: list[float] = []
        original = evaluate_stage.Evaluate.build

        def timed(self: Any, out: Path, key: str) -> dict[str, Any]:
            start = time.perf_counter()
            try:
                return original(self, out, key)
            finally:
                stage_times.append(time.perf_counter() - start)

        evaluate_stage.Evaluate.build = timed  # type: ignore[method-assign]
        runs = []
        try:
            bare()  # warm-up
            before = bare()
            for _ in range(repeats):
                run(again)
                after = bare()
                forward = (before + after) / 2
                runs.append({"bare_ms": 1000 * forward / n, "stage_ms": 1000 * stage_times[-1] / n,
                             "ratio": forward / stage_times[-1]})
                before = after
        finally:
            evaluate_stage.Evaluate.build = original  # type: ignore[method-assign]
            models.build_model = build
    median = sorted(runs, key=lambda r: r["ratio"])[len(runs) // 2]
    return {**median, "ratios": [round(r["ratio"], 3) for r in runs], "images": n, "groups": groups,
            "width": width, "height": height, "model": model, "threads": threads,
            "ratio_spread": max(r["ratio"] for r in runs) - min(r["ratio"] for r in runs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--groups", type=int, default=8)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--model", default="tiny_fcos")
    ap.add_argument("--zoo", action="store_true", help="the model's own config (a trained zoo member), not zoo widths")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    r = measure(a.groups, a.width, a.height, a.model, a.zoo, a.repeats, a.threads)
    if a.json:
        print(json.dumps(r))
        return
    print(f"{r['model']} on {r['groups']} groups x {r['images'] // r['groups']} conditions at {r['width']}x{r['height']}, "
          f"{r['threads']} threads")
    print(f"  bare forward {r['bare_ms']:.1f} ms an image; evaluate stage {r['stage_ms']:.1f} ms an image")
    print(f"  stage / bare forward (throughput): {r['ratio']:.2f} (median of {r['ratios']}, spread "
          f"{r['ratio_spread']:.2f}; target >= 0.9 on the CPU)")


if __name__ == "__main__":
    main()
