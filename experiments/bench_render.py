"""Seconds per image and per scene of the Blender backend, split into construction and
condition-wise rendering.

    python experiments/bench_render.py                      # 512x256 and 1024x512, 2 scenes x 9 conditions
    python experiments/bench_render.py --sizes 512x256 --scenes 3 samples=8 denoise=false
    python experiments/bench_render.py --sweep              # a few quality/speed settings at 512x256
    python experiments/bench_render.py fog_model=volume --sizes 512x256   # path-traced fog instead of analytic
    python experiments/bench_render.py --contact /tmp/blender_contact.png   # 9 conditions + labels of scene 0
    python experiments/bench_render.py --sizes 512x256 --no-population     # without the ambient population

Trailing key=value pairs override pairedgta/conf/renderer/blender.yaml (`camera=<preset>` picks the camera). Wall time is what a user waits; CPU
seconds / cores is printed beside it because a shared machine inflates wall time (the load average
is printed too, so numbers from a busy machine can be recognised).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pairedgta.conditions import build_condition_grid
from pairedgta.render.blender import BlenderRenderer
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.placement import PlacementConfig, place_objects
from pairedgta.scene.town import ProceduralTownRegion

SWEEP = [
    {"samples": 1},
    {"samples": 2},
    {"samples": 4},
    {"samples": 2, "denoise": False},
    {"samples": 2, "max_bounces": 1},
    {"samples": 2, "fast_gi": False},
    {"samples": 2, "light_tree": True},
    {"samples": 2, "denoiser_quality": "BALANCED"},
    {"samples": 2, "fog_model": "volume"},
]


def _value(text: str):
    return OmegaConf.to_container(OmegaConf.create({"v": OmegaConf.from_dotlist([f"v={text}"])["v"]}))["v"]


def load_cfg(overrides: list[str]) -> tuple[dict, dict]:
    from pairedgta.testing.cli import compose_cfg

    camera = [o for o in overrides if o.startswith("camera=")]  # a camera preset, e.g. camera=fixed
    cfg = OmegaConf.to_container(compose_cfg(["renderer=blender", "region=procedural_town", *camera]), resolve=True)
    renderer, region = cfg["renderer"], cfg["region"]
    renderer.pop("backend")
    overrides = [o for o in overrides if o not in camera]
    for item in overrides:
        key, _, text = item.partition("=")
        renderer[key] = _value(text)
    return renderer, region


def descriptors(region_cfg: dict, n: int, seed: int, population: bool = True) -> list[SceneDescriptor]:
    """n scenes with 3-6 dynamic objects each and, unless `population` is off, the region's ambient
    population (as the generate stage adds it)."""
    region = ProceduralTownRegion(**{k: v for k, v in region_cfg.items() if k != "type"})
    out = []
    for k in range(n):
        rng = np.random.default_rng(seed + k)
        loc = region.sample_location(rng)
        objects, requested = place_objects(rng, loc, region, PlacementConfig(min=3, max=6))
        d = SceneDescriptor(scene_id=f"{k:05d}", seed=seed + k, location=loc, objects=objects,
                            region=region.name, requested_objects=requested)
        out.append(region.populate(d) if population else d)
    return out


def bench(renderer_cfg: dict, scenes: list[SceneDescriptor], grid, cores: int) -> dict:
    r = BlenderRenderer(**renderer_cfg)
    t = time.perf_counter()
    r.open()
    open_s = time.perf_counter() - t
    rows = []
    for d in scenes:
        c0, w0 = time.process_time(), time.perf_counter()
        r.prepare(d)
        prep = {"wall": time.perf_counter() - w0, "cpu": (time.process_time() - c0) / cores, **r.timings}
        images = []
        for cond in grid:
            c0, w0 = time.process_time(), time.perf_counter()
            r.render(d, cond)
            images.append({"condition": cond.name, "wall": time.perf_counter() - w0,
                           "cpu": (time.process_time() - c0) / cores})
        rows.append({"scene": d.scene_id, "prepare": prep, "images": images})
    r.close()
    per_image = [i["wall"] for row in rows for i in row["images"]]
    per_image_cpu = [i["cpu"] for row in rows for i in row["images"]]
    prep_wall = [row["prepare"]["wall"] for row in rows]
    label = [row["prepare"].get("label_pass", 0.0) for row in rows]
    n = len(grid)
    # CPU seconds of one whole scene (construction, label pass, every condition): what a core-hour buys
    scene_cpu = statistics.mean(cores * (row["prepare"]["cpu"] + sum(i["cpu"] for i in row["images"])) for row in rows)
    return {
        "scene_cpu_s": scene_cpu, "scenes_per_core_hour": 3600.0 / scene_cpu,
        "open_s": open_s,
        "image_wall_median": statistics.median(per_image), "image_wall_mean": statistics.mean(per_image),
        "image_cpu_mean": statistics.mean(per_image_cpu),
        # per image including the amortised label pass (once per scene)
        "image_incl_labels_mean": statistics.mean(per_image) + statistics.mean(label) / n,
        "construction_first": prep_wall[0], "construction_next": statistics.mean(prep_wall[1:] or prep_wall),
        "label_pass_mean": statistics.mean(label),
        "scene_wall_mean": statistics.mean(prep_wall[1:] or prep_wall) + statistics.mean(per_image) * n,
        "by_condition": {c.name: statistics.mean(row["images"][k]["wall"] for row in rows) for k, c in enumerate(grid)},
        "rows": rows,
    }


def contact_sheet(renderer_cfg: dict, scene: SceneDescriptor, grid, path: Path) -> None:
    """Conditions in a 3-column grid, then the label map, instance map and reference image."""
    from PIL import Image, ImageDraw

    from pairedgta.cityscapes import colorize

    with BlenderRenderer(**renderer_cfg) as r:
        results = [(c.name, r.render(scene, c)) for c in grid]
    ref = results[0][1]
    inst = ref.instances.astype(np.int64)
    inst_rgb = np.where(inst[..., None] > 0, (np.stack([inst * 67, inst * 151, inst * 229], -1) % 200) + 55, 0)
    tiles = [(n, res.image) for n, res in results] + [
        ("labels (all conditions)", colorize(ref.labels)), ("instances", inst_rgb.astype(np.uint8)),
        (results[0][0], ref.image)]
    h, w = ref.image.shape[:2]
    cols = 3
    sheet = Image.new("RGB", (cols * w, -(-len(tiles) // cols) * h))
    draw = ImageDraw.Draw(sheet)
    for k, (name, img) in enumerate(tiles):
        x, y = (k % cols) * w, (k // cols) * h
        sheet.paste(Image.fromarray(img), (x, y))
        draw.rectangle([x, y, x + 7 * len(name) + 6, y + 14], fill=(0, 0, 0))
        draw.text((x + 3, y + 2), name, fill=(255, 255, 255))
    sheet.save(path)
    print(f"# contact sheet: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["512x256", "1024x512"])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sweep", action="store_true", help="compare the SWEEP settings at the first size")
    ap.add_argument("--json", type=Path, default=None, help="write all numbers here")
    ap.add_argument("--contact", type=Path, default=None, help="only save a contact sheet of scene 0 here")
    ap.add_argument("--no-population", action="store_true", help="scenes without the ambient population")
    ap.add_argument("overrides", nargs="*", help="renderer key=value")
    args = ap.parse_args()
    renderer_cfg, region_cfg = load_cfg(args.overrides)
    grid = build_condition_grid(OmegaConf.to_container(OmegaConf.load(ROOT / "pairedgta" / "conf" / "conditions" / "paper.yaml")))
    scenes = descriptors(region_cfg, args.scenes, args.seed, population=not args.no_population)
    cores = os.cpu_count() or 1
    if args.contact:
        w, h = (int(v) for v in args.sizes[0].split("x"))
        contact_sheet({**renderer_cfg, "width": w, "height": h}, scenes[0], grid, args.contact)
        return
    print(f"# cores={cores} load_avg_before={os.getloadavg()[0]:.2f} scenes={len(scenes)} conditions={len(grid)} "
          f"ambient entities/scene={statistics.mean(len(d.ambient) for d in scenes):.1f}")
    results = {}
    runs = []
    if args.sweep:
        w, h = (int(v) for v in args.sizes[0].split("x"))
        runs = [(f"{w}x{h} " + " ".join(f"{k}={v}" for k, v in s.items()),
                 {**renderer_cfg, "width": w, "height": h, **s}) for s in SWEEP]
    else:
        for size in args.sizes:
            w, h = (int(v) for v in size.split("x"))
            runs.append((f"{w}x{h}", {**renderer_cfg, "width": w, "height": h}))
    print("| setting | s/image (median) | s/image CPU/cores | s/image incl. labels | label pass "
          "| construction first / next | s/scene (9 cond.) |")
    print("|---|---|---|---|---|---|---|")
    for name, cfg in runs:
        res = bench(cfg, scenes, grid, cores)
        results[name] = res
        print(f"| {name} | {res['image_wall_median']:.2f} | {res['image_cpu_mean']:.2f} "
              f"| {res['image_incl_labels_mean']:.2f} | "
              f"{res['label_pass_mean']:.2f} | {res['construction_first']:.2f} / {res['construction_next']:.2f} | "
              f"{res['scene_wall_mean']:.2f} |", flush=True)
    for name, res in results.items():
        print(f"# {name}: {res['scene_cpu_s']:.1f} CPU-s per scene of {len(grid)} conditions = "
              f"{res['scenes_per_core_hour']:.0f} scenes per core-hour")
    for name, res in results.items():
        print(f"# {name} by condition: " + ", ".join(f"{k} {v:.2f}" for k, v in res["by_condition"].items()))
    print(f"# load_avg_after={os.getloadavg()[0]:.2f}")
    if args.json:
        from pairedgta.jsonio import write_json

        write_json(args.json, results)


if __name__ == "__main__":
    main()
