"""Fit the night street's light (`renderer.night`, pairedgta/render/blender/illumination.py: NightLight) to the
authors' GTA V night frames, so that `python -m pairedgta +experiment=photometric_calibration` passes its checks
on any scenes, not only on the ones it was tuned on.

    python experiments/fit_night_light.py                     # 16 scenes of seeds 2 and 3, 256x128, 2 samples
    python experiments/fit_night_light.py --seeds 0 1 --size 256x128 --samples 2 --fill 0 0.01 0.02 --windows 1 2
    python experiments/fit_night_light.py --check-groups <plot entry>/photometry_groups.csv   # every 6 groups

Cycles is linear in every light's power: per scene and night condition the script renders the image with every
night term off and then with one term at a time (`BlenderRenderer.render_linear`, scene-referred, the fog compositor
included: its blend toward the in-scattered light is affine in the light), so the image of any NightLight is a
weighted sum of those renders, developed by the same camera (`BlenderRenderer.develop`). A grid of NightLight
values is then measured without rendering again (the fog's glare around lamps and the denoiser are the only
non-linear steps: `--verify` renders the chosen point and prints the model's error). The statistic and the
checks are the experiment's own (pairedgta/metrics/photometry.py, the bands of
pairedgta/conf/experiment/photometric_calibration.yaml): a point is feasible when every check passes on every
set: each seed's scenes and every run of `--subset` consecutive scenes among them; among the feasible points
the one nearest GTA V's Night-RAIN medians (squared log-ratios of luma and contrast) wins, ties to the lower
fill. Only the checks that name a night decide (no night term changes a day or sunset image); a failing check of
another condition (Sunset-FOGGY's band) is printed with the result. Writes every point to <out>/fit.csv, the
winner's checks to <out>/checks.csv and its per-group ratios to <out>/groups.csv; prints the `renderer.night`
lines for pairedgta/conf/renderer/blender.yaml. The renders are kept in <out> for a rerun with another grid.

What the searches found (2-core machine, Blender 5.0.1): a fill light alone raises the night's luma but hardly
its contrast, which comes from a few percent of near-white pixels: head-light lenses facing the camera, their
reflections on the wet road, lit windows and shop fronts. The main job's scenes 3-5 have oncoming head lights,
so every run of 6 of its scenes holds three of them; at the physical powers those scenes keep 0.6-0.76 of the
clean contrast (GTA V's twelve frames: 0.07-0.29). Dimming the head lights at every time of day lowers
Sunset-FOGGY's contrast under its band, hence terms that act at night only. The default grid (240 points, 90 s
with the renders kept, 4 min without) chooses fill 0.035, lamps 0.5, head lights 0.03, windows 0.1: Night-RAIN
luma 0.10 and contrast 0.14-0.16 of the clean image on the fit's sets (GTA V 0.123, 0.123); the model is within
0.4-0.8 grey levels of a real render. Checked at 512x256 by the experiment, neither seed used by the fit:
    main job (seed 0)   Night-RAIN luma 0.110, contrast 0.158 (before: 0.116, 0.348); its runs of 6 scenes
                        0.182-0.198; 16 of 16 checks (Blender 5.3.0: 0.111, 0.157)
    seed=1              0.114, 0.153; 16 of 16 (Blender 5.3.0: 0.114, 0.154)
Outside the night (not changed by it): the sunset was left at its edge (the main job's scenes 1-6 gave Sunset-RAIN a
median luma 0.0008 above Sunset-EXTRASUNNY, runs of 6 of seeds 2 and 3 Sunset-FOGGY's contrast ratio 0.39, under its
band's 0.40), and has its own fit since: experiments/fit_sunset_light.py (renderer.sunset). A failing check of a
sunset is printed with the result here, not fitted.
"""
from __future__ import annotations

import argparse
import hashlib
import itertools
import math
import pickle
import time
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pairedgta import schema
from pairedgta.cache import canonical_json
from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.conditions import build_condition_grid
from pairedgta.filehash import sha256_file
from pairedgta.metrics.photometry import band_checks, group_rows, physics_checks, summarise
from pairedgta.render import build_renderer, renderer_versions
from pairedgta.render.blender.illumination import NightLight, lighting
from pairedgta.scene.sampling import build_region
from pairedgta.stages.generate import VERSION, build_descriptor
from pairedgta.testing.cli import compose_cfg

TERMS = ("fill", "lamps", "headlights", "windows")
BACKEND = Path(__file__).resolve().parents[1] / "pairedgta" / "render" / "blender"  # the renders' code
FILL_UNIT = 0.02  # the fill term is rendered at this radiance and scaled (linear)
OFF = NightLight(fill=0.0, lamps=0.0, headlights=0.0, windows=0.0)


def unit(term: str) -> NightLight:
    return NightLight(**{t: (FILL_UNIT if t == "fill" else 1.0) if t == term else 0.0 for t in TERMS})


def render_parts(renderer, descriptor, grid) -> dict[str, dict]:
    """Per condition: the image and labels where NightLight changes nothing (day, sunset), else the render with
    every night term off and each term's share (a night: the `night` weight 1, where every term applies fully)."""
    parts: dict[str, dict] = {}
    for cond in grid:
        night = lighting(cond)["night"]
        if night == 0.0:
            res = renderer.render(descriptor, cond)
            parts[cond.name] = {"image": res.image, "labels": res.labels}
            continue
        if night != 1.0:
            raise SystemExit(f"{cond.name}: between day and night (night weight {night:.2f}); fit on a grid of days, "
                             "sunsets and full nights (conditions=paper)")
        base, _ = renderer.render_linear(descriptor, cond, OFF)
        shares = {}
        for term in TERMS:
            image, _ = renderer.render_linear(descriptor, cond, unit(term))
            shares[term] = (image - base) / (FILL_UNIT if term == "fill" else 1.0)
        parts[cond.name] = {"base": base, "shares": shares}
    return parts


def develop_all(renderer, scenes: list[dict], grid, light: NightLight) -> list[dict[str, np.ndarray]]:
    """The 8-bit images of every scene and condition under `light`, developed in one call per exposure."""
    return develop_linear(renderer, scenes, grid,
                          lambda part, cond: part["base"] + sum(getattr(light, t) * s for t, s in part["shares"].items()),
                          lambda cond: lighting(cond, light)["light_level"])


def develop_linear(renderer, scenes: list[dict], grid, linear, light_level) -> list[dict[str, np.ndarray]]:
    """Every fit's development: `linear(part, cond)` the modelled scene-referred image of a part not rendered in
    full, `light_level(cond)` what sets the camera's exposure; parts with an "image" are kept as rendered. One
    develop call per exposure."""
    camera = renderer.camera
    stacks: dict[float, list[tuple[int, str, np.ndarray]]] = {}
    for i, parts in enumerate(scenes):
        for cond in grid:
            part = parts[cond.name]
            if "image" in part:
                continue
            ev = round(camera.exposure(cond, light_level(cond)), 6)
            stacks.setdefault(ev, []).append((i, cond.name, linear(part, cond)))
    out: list[dict[str, np.ndarray]] = [{n: p["image"] for n, p in parts.items() if "image" in p} for parts in scenes]
    for ev, items in stacks.items():
        h = items[0][2].shape[0]
        developed = renderer.develop(np.concatenate([x for _, _, x in items]), ev)
        for j, (i, name, _) in enumerate(items):
            out[i][name] = developed[j * h:(j + 1) * h]
    return out


def scene_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every light fit shares: which scenes, at which size."""
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3], help="the scenes' seeds (generate.seed)")
    ap.add_argument("--scenes", type=int, default=8, help="scenes per seed")
    ap.add_argument("--subset", type=int, default=6, help="every run of this many consecutive scenes must pass too")
    ap.add_argument("--size", default="256x128", help="WIDTHxHEIGHT of the renders")
    ap.add_argument("--samples", type=int, default=2)


def run_arguments(ap: argparse.ArgumentParser, out: str) -> argparse.Namespace:
    """The shared last options, then the parsed command line."""
    ap.add_argument("--verify", action="store_true", help="render the chosen point and print the model's error")
    ap.add_argument("--out", type=Path, default=Path("outputs") / out)
    ap.add_argument("--check-groups", type=Path, default=None, metavar="CSV",
                    help="no fit: the checks on every run of --subset consecutive groups of an experiment's "
                         "photometry_groups.csv")
    args = ap.parse_args()
    return args


def setup(args: argparse.Namespace, condition: str) -> tuple[list[str], dict, dict, object, dict]:
    """The fit's config (overrides, composed config, photometry settings, condition grid) and GTA V's median luma
    and contrast ratios of `condition`; `--check-groups` alone checks a CSV and exits."""
    if args.check_groups:
        raise SystemExit(0 if check_groups(args.check_groups, args.subset) else 1)
    width, height = (int(v) for v in args.size.split("x"))

    base = ["+experiment=photometric_calibration", f"renderer.width={width}", f"renderer.height={height}",
            f"renderer.samples={args.samples}"]
    cfg = OmegaConf.to_container(compose_cfg(base), resolve=True)
    settings = cfg["photometry"]
    grid = build_condition_grid(cfg["conditions"])
    from pairedgta.figures.photometry import reference_table

    gta_row = reference_table().set_index("condition").loc[condition]
    gta = {"luma": float(gta_row["luma_ratio_median"]), "contrast": float(gta_row["contrast_ratio_median"])}
    return base, cfg, settings, grid, gta


def cached_renders(renderer, out: Path, what: dict, seeds: list[int], n: int, base: list[str], grid, t0: float,
                   render=None) -> tuple[list[dict], list, list]:
    """The fit's renders of `n` scenes per seed, kept under `out` named by `what` (what decides them), so a rerun
    with another grid of light values renders nothing. `render(renderer, descriptor, grid)`: a fit's own parts
    (default: this fit's `render_parts`)."""
    store = out / f"renders-{hashlib.sha256(canonical_json(what).encode()).hexdigest()[:12]}.pkl"
    scenes, labels, descriptors = [], [], []
    if store.is_file():
        scenes, descriptors = pickle.loads(store.read_bytes())
        labels = [parts[grid.reference]["labels"] for parts in scenes]
        print(f"renders from {store}")
        return scenes, labels, descriptors
    for seed in seeds:
        run = schema.parse(OmegaConf.to_container(compose_cfg([*base, f"seed={seed}"]), resolve=True))
        region = build_region(run.region)
        for k in range(n):
            descriptor, _ = build_descriptor(k, run.generate, region)
            parts = (render or render_parts)(renderer, descriptor, grid)
            scenes.append(parts)
            labels.append(parts[grid.reference]["labels"])
            descriptors.append(descriptor)
            print(f"seed {seed} scene {k}: rendered ({time.perf_counter() - t0:.0f} s)", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    store.write_bytes(pickle.dumps((scenes, descriptors)))
    return scenes, labels, descriptors


def sets(seeds: list[int], n: int, subset: int) -> dict[str, list[int]]:
    """Scene index sets (into the seeds' scenes in order): each seed's, and its runs of `subset` scenes."""
    found: dict[str, list[int]] = {}
    for j, seed in enumerate(seeds):
        idx = list(range(j * n, (j + 1) * n))
        found[f"seed {seed}"] = idx
        if subset and subset < n:
            for s in range(n - subset + 1):
                found[f"seed {seed} scenes {s}-{s + subset - 1}"] = idx[s:s + subset]
    return found


def evaluate(images, labels, grid, settings, gta, chosen: dict[str, list[int]]) -> tuple[dict, list[dict]]:
    """The experiment's checks on every set; the Night-RAIN medians and the distance to GTA V on the first."""
    sky = CLASS_NAMES.index("sky")
    reference = grid.reference
    conditions = {c.name: c for c in grid.conditions}
    order = [reference, *[n for n in grid.names if n != reference]]
    rows = group_rows(((i, images[i], labels[i]) for i in range(len(images))), reference, sky)
    result: dict = {}
    failed: list[dict] = []
    others: list[dict] = []  # checks no night term changes (Sunset-FOGGY's band): reported, not fitted
    worst_contrast = 0.0
    for name, idx in chosen.items():
        summary = summarise([r for r in rows if r["group_id"] in set(idx)], order)
        checks = band_checks(summary, settings["bands"]) + physics_checks(
            summary, conditions, reference, float(settings["night_max_luma_ratio"]), float(settings["night_sky_max_luma"]))
        failed += [{"set": name, **c} for c in checks if not c["ok"] and "Night" in c["check"]]
        others += [{"set": name, **c} for c in checks if not c["ok"] and "Night" not in c["check"]]
        by = {r["condition"]: r for r in summary}
        worst_contrast = max(worst_contrast, by["Night-RAIN"]["contrast_ratio_median"])
    summary = summarise(rows, order)
    by = {r["condition"]: r for r in summary}
    luma, contrast = by["Night-RAIN"]["luma_ratio_median"], by["Night-RAIN"]["contrast_ratio_median"]
    result.update(luma=luma, contrast=contrast, worst_contrast=worst_contrast, failed=len(failed),
                  not_night=("; ".join(f"{c['set']}: {c['check']} ({c['value']})" for c in others)),
                  error=math.log(luma / gta["luma"]) ** 2 + math.log(contrast / gta["contrast"]) ** 2)
    return result, failed


def check_groups(path: Path, subset: int) -> bool:
    """The experiment's checks on every run of `subset` consecutive groups of a photometry_groups.csv (the plot
    stage's output of +experiment=photometric_calibration), and on all of them; prints one line per set."""
    cfg = OmegaConf.to_container(compose_cfg(["+experiment=photometric_calibration"]), resolve=True)
    settings, grid = cfg["photometry"], build_condition_grid(cfg["conditions"])
    conditions = {c.name: c for c in grid.conditions}
    order = [grid.reference, *[n for n in grid.names if n != grid.reference]]
    rows = pd.read_csv(path).to_dict("records")
    ids = sorted({r["group_id"] for r in rows})
    runs = {"all": ids, **{f"groups {ids[s]}-{ids[s + subset - 1]}": ids[s:s + subset]
                           for s in range(len(ids) - subset + 1)}} if subset < len(ids) else {"all": ids}
    ok = True
    for name, chosen in runs.items():
        summary = summarise([r for r in rows if r["group_id"] in chosen], order)
        checks = band_checks(summary, settings["bands"]) + physics_checks(
            summary, conditions, grid.reference, float(settings["night_max_luma_ratio"]), float(settings["night_sky_max_luma"]))
        by = {r["condition"]: r for r in summary}
        failed = [f"{c['check']} ({c['value']})" for c in checks if not c["ok"]]
        ok &= not failed
        print(f"{name}: {len(checks) - len(failed)} of {len(checks)} checks pass; Night-RAIN luma "
              f"{by['Night-RAIN']['luma_ratio_median']:.3f} contrast {by['Night-RAIN']['contrast_ratio_median']:.3f}, "
              f"Sunset-FOGGY luma {by['Sunset-FOGGY']['luma_ratio_median']:.3f} contrast "
              f"{by['Sunset-FOGGY']['contrast_ratio_median']:.3f}" + (f"; failed: {'; '.join(failed)}" if failed else ""))
    return ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    scene_arguments(ap)
    ap.add_argument("--max-contrast", type=float, default=0.22,
                    help="Night-RAIN's median contrast ratio on every set at most this (the issue's 0.25, less a margin "
                         "for the step to 512x256)")
    # the grid around the optimum of wider searches (the docstring), with the physical model's own powers
    ap.add_argument("--fill", type=float, nargs="+", default=[0.0, 0.03, 0.035, 0.04, 0.045, 0.05])
    ap.add_argument("--lamps", type=float, nargs="+", default=[0.5, 1.0])
    ap.add_argument("--headlights", type=float, nargs="+", default=[0.02, 0.03, 0.05, 0.1, 1.0])
    ap.add_argument("--windows", type=float, nargs="+", default=[0.05, 0.1, 0.2, 1.0])
    args = run_arguments(ap, "fit_night_light")
    base, cfg, settings, grid, gta = setup(args, "Night-RAIN")

    t0 = time.perf_counter()
    # the renders, kept for a rerun with another grid: named by what decides them
    what = {"seeds": args.seeds, "scenes": args.scenes, "renderer": cfg["renderer"], "grid": grid.names,
            "blender": renderer_versions("blender"), "generate": VERSION,
            "code": [sha256_file(f) for f in sorted(BACKEND.glob("*.py"))]}
    with build_renderer(cfg["renderer"]) as renderer:
        scenes, labels, descriptors = cached_renders(renderer, args.out, what, args.seeds, args.scenes, base, grid, t0)

        chosen = sets(args.seeds, args.scenes, args.subset)
        points = []
        for values in itertools.product(args.fill, args.lamps, args.headlights, args.windows):
            light = NightLight(*values)
            images = develop_all(renderer, scenes, grid, light)
            result, failed = evaluate(images, labels, grid, settings, gta, chosen)
            feasible = result["failed"] == 0 and result["worst_contrast"] <= args.max_contrast
            points.append({**dict(zip(TERMS, values)), **result, "feasible": feasible,
                           "first_failure": f"{failed[0]['set']}: {failed[0]['check']} ({failed[0]['value']})" if failed else ""})
            print(f"{light}: Night-RAIN luma {result['luma']:.3f} contrast {result['contrast']:.3f} "
                  f"(worst set {result['worst_contrast']:.3f}), error {result['error']:.3f}, "
                  f"{result['failed']} failed checks", flush=True)
        table = pd.DataFrame(points)
        args.out.mkdir(parents=True, exist_ok=True)
        table.to_csv(args.out / "fit.csv", index=False, float_format="%.4f")
        feasible = table[table["feasible"]].sort_values(["error", "fill"])
        if feasible.empty:
            print(f"no point passes every check on every set with contrast <= {args.max_contrast}; widen the grid "
                  f"({args.out / 'fit.csv'})")
            raise SystemExit(1)
        best = feasible.iloc[0]
        light = NightLight(**{t: float(best[t]) for t in TERMS})
        images = develop_all(renderer, scenes, grid, light)
        sky = CLASS_NAMES.index("sky")
        groups = group_rows(((i, images[i], labels[i]) for i in range(len(images))), grid.reference, sky)
        pd.DataFrame(groups).to_csv(args.out / "groups.csv", index=False, float_format="%.4f")
        rows = []
        for name, idx in chosen.items():
            sub = [images[i] for i in idx]
            result, failed = evaluate(sub, [labels[i] for i in idx], grid, settings, gta, {name: list(range(len(idx)))})
            rows.append({"set": name, "night_rain_luma": result["luma"], "night_rain_contrast": result["contrast"],
                         "failed": result["failed"], "failed_not_night": result["not_night"]})
        pd.DataFrame(rows).to_csv(args.out / "checks.csv", index=False, float_format="%.4f")
        print(pd.DataFrame(rows).to_string(index=False, float_format="%.3f"))
        if args.verify:
            verify(renderer, scenes, descriptors, grid, light)
    print(f"\n{len(points)} points, {time.perf_counter() - t0:.0f} s; chosen (pairedgta/conf/renderer/blender.yaml):")
    print("night:\n" + "".join(f"  {t}: {getattr(light, t):g}\n" for t in TERMS), end="")


def verify(renderer, scenes, descriptors, grid, light: NightLight) -> None:
    """The model against a real render of the chosen point: mean absolute difference in grey levels and the
    Night-RAIN contrast of each, on the first two scenes."""
    saved, renderer.night = renderer.night, light
    try:
        model = develop_all(renderer, scenes[:2], grid, light)
        for i in range(min(2, len(scenes))):
            for name in ("Night-EXTRASUNNY", "Night-RAIN", "Night-FOGGY", "Sunset-FOGGY"):
                real = renderer.render(descriptors[i], grid[name]).image
                diff = np.abs(real.astype(int) - model[i][name].astype(int)).mean()
                print(f"verify scene {i} {name}: model vs render {diff:.2f} grey levels")
    finally:
        renderer.night = saved


if __name__ == "__main__":
    main()
