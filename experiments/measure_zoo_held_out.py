"""The offline zoo's held-out mIoU on freshly rendered held-out scenes: the 24 Day-EXTRASUNNY scenes of the 4 unseen
towns that training validates on (pairedgta/conf/train_demo.yaml: data.val_*), rendered by this interpreter's Blender
through the cached generate stage, then every zoo member's mIoU (Cityscapes convention, as the model cards').

    python experiments/measure_zoo_held_out.py                      # all twelve, cache in outputs/cache
    python experiments/measure_zoo_held_out.py --models demo_segformer demo_ddrnet --out zoo_held_out.csv

On the Blender the zoo was trained with, the numbers are the cards'; on another (bpy 5.3 on Python 3.13) they say
whether the zoo still holds on that renderer's pixels (issue 51: a member below 0.35 is retrained).
"""
from __future__ import annotations

import argparse
import importlib.metadata
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))

from train_demo_model import render_towns

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.conditions import build_condition_grid
from pairedgta.metrics import ConfusionMatrix


def compose(overrides: list[str]) -> dict:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module

    with initialize_config_module(config_module="pairedgta.conf", version_base="1.3"):
        return OmegaConf.to_container(hydra_compose(config_name="train_demo", overrides=overrides), resolve=True)


def main() -> None:
    from pairedgta.models import build_model
    from pairedgta.testing.cli import compose_cfg

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=None, help="zoo members (default: every one, +experiment=zoo)")
    ap.add_argument("--cache-dir", default="outputs/cache")
    ap.add_argument("--out", type=Path, default=None, help="write the table here as CSV")
    args = ap.parse_args()
    models = args.models or list(compose_cfg(["+experiment=zoo"]).models)
    cfg = compose([f"cache_dir={args.cache_dir}", "model_name=held_out"])
    d = cfg["data"]
    grid = build_condition_grid({**cfg["conditions"], "only": [cfg["condition"]]})
    t0 = time.perf_counter()
    images, labels, _ = render_towns(cfg, grid, range(d["val_town_seed"], d["val_town_seed"] + d["val_towns"]),
                                     d["val_scenes_per_town"], d["scene_seed"] + 100_000)
    render_s = time.perf_counter() - t0
    rows = []
    for name in models:
        seg = build_model(name)
        cm = ConfusionMatrix(NUM_CLASSES)
        for i in range(0, len(images), 4):
            pred, _ = seg.predict(np.stack(images[i:i + 4]))
            for truth, p in zip(labels[i:i + 4], pred):
                cm.update(truth, np.asarray(p))
        iou = cm.iou().numpy()
        rows.append({"model": name, "held_out_miou": float(np.nanmean(iou))})
        print(f"{name}: {rows[-1]['held_out_miou']:.3f}", flush=True)
    table = pd.DataFrame(rows)
    try:
        blender = importlib.metadata.version("bpy")
    except importlib.metadata.PackageNotFoundError:
        blender = "none"
    print(f"{len(images)} held-out scenes rendered by Blender {blender} in {render_s:.0f} s (cached: 0 s); "
          f"Python {sys.version_info.major}.{sys.version_info.minor}")
    if args.out:
        table.assign(blender_version=blender).to_csv(args.out, index=False, float_format="%.4f")


if __name__ == "__main__":
    main()
