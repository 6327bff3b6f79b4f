"""Class statistics of the embedded Blender world beside Cityscapes: per-class pixel share over N
Day-EXTRASUNNY scenes, the share of scenes that contain each class, and the KL divergence between
the two class distributions. Scenes are built as the generate stage builds them (location, the 0-3
dynamic objects) plus the region's ambient population.

    python experiments/bench_classes.py                    # 32 scenes at 512x256
    python experiments/bench_classes.py --scenes 8 --json /tmp/classes.json
    python experiments/bench_classes.py population.pedestrians_per_100m=0   # region overrides

Trailing key=value pairs override conf/region/procedural_town.yaml (dotted keys reach into
`population`). Only the label pass matters here, so the beauty pass runs at 1 sample without
denoising.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.conditions import build_condition_grid
from pairedgta.render.blender import BlenderRenderer
from pairedgta.scene.town import ProceduralTownRegion
from pairedgta import schema
from pairedgta.stages.generate import build_descriptor

# Cityscapes gtFine train: share of all pixels per class, in percent (train ids 0..18). Source: the
# "pixel-wise occ [%]" column of cityscapes.md in github.com/m-birke/automotive-segmentation-datasets,
# counted over the 2975 fine training label maps. They are renormalised over the 19 classes below
# (the rest of the pixels are void: ego vehicle, rectification border, out of roi, static, ...).
CITYSCAPES_FINE_TRAIN_PERCENT = {
    "road": 32.7, "sidewalk": 5.3, "building": 20.1, "wall": 0.59, "fence": 0.77, "pole": 1.1243,
    "traffic light": 0.1823, "traffic sign": 0.5015, "vegetation": 14.3, "terrain": 0.98, "sky": 3.5,
    "person": 1.1, "rider": 0.1295, "car": 6.0, "truck": 0.2406, "bus": 0.2271, "train": 0.1907,
    "motorcycle": 0.0848, "bicycle": 0.4030,
}
TARGETS = {"car_share": 0.04, "person_share": 0.005, "car_scenes": 0.8, "person_scenes": 0.5}
EPS = 1e-6  # floor for KL: a class that never appears would make it infinite


def kl(p: np.ndarray, q: np.ndarray) -> float:
    p = np.maximum(p, EPS) / np.maximum(p, EPS).sum()
    q = np.maximum(q, EPS) / np.maximum(q, EPS).sum()
    return float(np.sum(p * np.log(p / q)))


def load_region(overrides: list[str]) -> dict:
    region = OmegaConf.load(ROOT / "pairedgta" / "conf" / "region" / "procedural_town.yaml")
    if overrides:
        region = OmegaConf.merge(region, OmegaConf.from_dotlist(overrides))
    cfg = OmegaConf.to_container(region)
    cfg.pop("type")
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0, help="generate.seed of the scenes")
    ap.add_argument("--size", default="512x256")
    ap.add_argument("--condition", default="Day-EXTRASUNNY")
    ap.add_argument("--json", type=Path, default=None, help="write the numbers here")
    ap.add_argument("overrides", nargs="*", help="region key=value")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    region_cfg = load_region(args.overrides)
    region = ProceduralTownRegion(**region_cfg)
    main_cfg = OmegaConf.load(ROOT / "pairedgta" / "conf" / "config.yaml")
    gen = OmegaConf.to_container(main_cfg.generate, resolve=False)
    gen_cfg = schema.parse({"generate": {"seed": args.seed, "objects": gen["objects"], "camera": gen["camera"]}}).generate
    grid = build_condition_grid(OmegaConf.to_container(OmegaConf.load(ROOT / "pairedgta" / "conf" / "conditions" / "paper.yaml")))
    cond = grid[args.condition]
    counts = np.zeros(NUM_CLASSES + 1, dtype=np.int64)  # last: void
    present = np.zeros(NUM_CLASSES, dtype=np.int64)
    ambient = []
    t0 = time.perf_counter()
    with BlenderRenderer(width=w, height=h, samples=1, denoise=False, town=region_cfg) as r:
        for k in range(args.scenes):
            d, _ = build_descriptor(k, gen_cfg, region)
            d = region.populate(d)
            ambient.append(len(d.ambient))
            labels = r.render(d, cond).labels
            c = np.bincount(np.minimum(labels.ravel(), NUM_CLASSES), minlength=NUM_CLASSES + 256)[: NUM_CLASSES + 1]
            counts += c
            present += c[:NUM_CLASSES] > 0
    seconds = time.perf_counter() - t0
    ours = counts[:NUM_CLASSES] / counts.sum()
    cs = np.array([CITYSCAPES_FINE_TRAIN_PERCENT[n] for n in CLASS_NAMES])
    cs = cs / cs.sum()
    scene_share = present / args.scenes
    print(f"# {args.scenes} scenes, {args.condition}, {w}x{h}; {np.mean(ambient):.1f} ambient entities/scene; "
          f"{seconds:.1f} s; load_avg={os.getloadavg()[0]:.2f}")
    print("| class | ours % of pixels | Cityscapes fine train % | scenes containing |")
    print("|---|---|---|---|")
    for i, name in enumerate(CLASS_NAMES):
        print(f"| {name} | {100 * ours[i]:.2f} | {100 * cs[i]:.2f} | {100 * scene_share[i]:.0f} % |")
    print(f"| (void) | {100 * counts[NUM_CLASSES] / counts.sum():.2f} | - | - |")
    kl_cs_ours, kl_ours_cs = kl(cs, ours), kl(ours, cs)
    print(f"# KL(Cityscapes || ours) = {kl_cs_ours:.3f} nats, KL(ours || Cityscapes) = {kl_ours_cs:.3f} nats "
          f"(class shares floored at {EPS})")
    car, person = CLASS_NAMES.index("car"), CLASS_NAMES.index("person")
    missing = [n for i, n in enumerate(CLASS_NAMES) if present[i] == 0 and n != "train"]
    checks = {
        f"car >= {100 * TARGETS['car_share']:.0f} % of pixels": ours[car] >= TARGETS["car_share"],
        f"person >= {100 * TARGETS['person_share']:.1f} % of pixels": ours[person] >= TARGETS["person_share"],
        "every class but train present" + (f" (missing: {', '.join(missing)})" if missing else ""): not missing,
        f"car in >= {100 * TARGETS['car_scenes']:.0f} % of scenes": scene_share[car] >= TARGETS["car_scenes"],
        f"person in >= {100 * TARGETS['person_scenes']:.0f} % of scenes":
            scene_share[person] >= TARGETS["person_scenes"],
    }
    for what, ok in checks.items():
        print(f"# target {what}: {'met' if ok else 'NOT met'}")
    if args.json:
        out = {
            "scenes": args.scenes, "condition": args.condition, "size": [w, h], "seconds": seconds,
            "ambient_mean": float(np.mean(ambient)),
            "share": {n: float(ours[i]) for i, n in enumerate(CLASS_NAMES)},
            "cityscapes_share": {n: float(cs[i]) for i, n in enumerate(CLASS_NAMES)},
            "scene_share": {n: float(scene_share[i]) for i, n in enumerate(CLASS_NAMES)},
            "kl_cityscapes_ours": kl_cs_ours, "kl_ours_cityscapes": kl_ours_cs,
            "targets": {k: bool(v) for k, v in checks.items()},
        }
        tmp = args.json.with_name(args.json.name + ".tmp")
        tmp.write_text(json.dumps(out, indent=2, allow_nan=False))
        os.replace(tmp, args.json)


if __name__ == "__main__":
    main()
