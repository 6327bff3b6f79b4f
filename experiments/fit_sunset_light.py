"""Fit the low sun's light under cloud and in haze (`renderer.sunset`, pairedgta/render/blender/illumination.py:
SunsetLight) to the authors' GTA V sunset frames, so that `python -m pairedgta +experiment=photometric_calibration`
passes its checks with a margin on any scenes: rain at sunset darker than the clear sunset (as in GTA V), and
Sunset-FOGGY's luma and contrast ratios inside their GTA V bands, not at an edge.

    python experiments/fit_sunset_light.py                    # 16 scenes of seeds 2 and 3, 256x128, 2 samples
    python experiments/fit_sunset_light.py --seeds 0 1 --overcast 0.5 1 --haze 1 1.5 --verify
    python experiments/fit_sunset_light.py --check-groups <plot entry>/photometry_groups.csv   # every 6 groups

Cycles is linear in every light's power and SunsetLight scales light only: the sun and the cloud base by
u = 1 + (overcast - 1) x cover x dusk, the haze's in-scattered colour F by haze (and by u, which lights it). The
analytic fog blends the render R toward F by the transmittance T (compositor), so the scene-referred image is
T R(u) + (1 - T) F(u, haze): bilinear in (u, haze). Per scene and sunset condition the script renders it at the
four corners u, haze in {0, 1} (`BlenderRenderer.render_linear`), so the image of any SunsetLight is their bilinear
blend, developed by the same camera (`BlenderRenderer.develop`); the fog's glare around bright lights and the
denoiser are the only non-linear steps (`--verify` renders the chosen point and prints the model's error). The
statistic and the checks are the experiment's own (pairedgta/metrics/photometry.py, the bands of
pairedgta/conf/experiment/photometric_calibration.yaml). A point is feasible when, on every set (each seed's
scenes and every run of `--subset` consecutive scenes among them), every one of the 16 checks passes, Sunset-RAIN's
median luma is at least `--rain-margin` under Sunset-EXTRASUNNY's, and Sunset-FOGGY's luma and contrast ratios lie
at least `--band-margin` inside their bands; among the feasible points the one nearest GTA V's Sunset-FOGGY medians
(squared log-ratios of luma and contrast, on all scenes) wins, ties to the smaller change from (1, 1). Writes every
point to <out>/fit.csv and the winner's checks per set to <out>/checks.csv; prints the `renderer.sunset` lines for
pairedgta/conf/renderer/blender.yaml. The renders are kept in <out> for a rerun with another grid.

What the fit found (2-core machine, Blender 5.0.1): Sunset-FOGGY's luma and contrast ratios rise together with the haze
(the sky and the far street take the haze's colour), the contrast a little faster where the street under the cloud is
darker; no point of the family reaches GTA V's contrast (0.557) at its luma (0.440), so the nearest trade one for the
other: luma 0.50-0.52 and contrast 0.47-0.49 of the clean image on the fit's scenes, error 0.042-0.047 against 0.099 for
the sky model's own (1, 1) (luma 0.454, contrast 0.407, and contrast under 0.40 on some runs of 6). The error hardly
depends on the overcast (fog's cover is half of rain's), which the rain's margin bounds from above; --tolerance picks,
among the 14 feasible points within 0.005 of the least error, the one nearest (1, 1): overcast 0.4, haze 1.8 (error
0.047). The default grid (380 points) takes 2.5 min with the renders kept, 3.5-5.5 min without; the model is within
0.06-0.74 grey levels of a real render. Checked at 512x256 by the experiment, neither seed used by the fit: main job
(seed 0) Sunset-RAIN 0.018-0.023 of luma under the clear sunset on its runs of 6 scenes and all 8 (before: 0.0008 over
on scenes 1-6), Sunset-FOGGY luma 0.503-0.549 and contrast 0.466-0.486 (before 0.432-0.495 and 0.402-0.432); seed=1:
0.037-0.046 under, luma 0.521-0.547, contrast 0.447-0.462 (before 0.019-0.028 under, luma 0.459-0.486, contrast
0.409-0.413); 16 of 16 checks on every set, under Blender 5.3.0 too (experiments/README.md).
"""
from __future__ import annotations

import argparse
import itertools
import math
import time

import numpy as np
import pandas as pd
from fit_night_light import (  # the script's folder (sys.path[0])
    BACKEND,
    cached_renders,
    develop_linear,
    run_arguments,
    scene_arguments,
    sets,
    setup,
)

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.filehash import sha256_file
from pairedgta.metrics.photometry import band_checks, group_rows, physics_checks, summarise
from pairedgta.render import build_renderer, renderer_versions
from pairedgta.render.blender.illumination import SUNSET, SunsetLight, lighting
from pairedgta.stages.generate import VERSION

TERMS = ("overcast", "haze")
PROBE = SunsetLight(overcast=0.5, haze=0.5)  # a SunsetLight unlike any fitted one: what it leaves alone, none does


def weight(cond, night) -> float:
    """cover x dusk: how much of SunsetLight.overcast a condition feels (u = 1 + (overcast - 1) x weight)."""
    p = lighting(cond, night)
    return float(p["cloud_cover"] * p["dusk"])


def corner(cond, night, u: float, haze: float) -> SunsetLight:
    """The SunsetLight whose cloud factor is `u` (possibly a negative overcast: a corner of the model, not a light)."""
    w = weight(cond, night)
    return SunsetLight(overcast=1.0 + (u - 1.0) / w if w > 0 else 1.0, haze=haze)


def changes(cond, night) -> bool:
    """Whether the image of `cond` depends on the SunsetLight: any render parameter but, in clear air (no compositor
    pass: shading.py), the fog colour."""
    a, b = lighting(cond, night, SUNSET), lighting(cond, night, PROBE)
    keys = [k for k in a if k != "fog_color" or a["extinction"] > 0]
    return not all(np.array_equal(np.asarray(a[k]), np.asarray(b[k])) for k in keys)


def render_parts(renderer, descriptor, grid) -> dict[str, dict]:
    """Per condition: the image and labels where SunsetLight changes nothing, else the scene-referred renders at
    the four corners (u, haze) of the bilinear model, `c<u><haze>`."""
    parts: dict[str, dict] = {}
    for cond in grid:
        if not changes(cond, renderer.night):
            res = renderer.render(descriptor, cond)
            parts[cond.name] = {"image": res.image, "labels": res.labels}
            continue
        if cond.extinction_per_m > 0 and renderer.fog_model != "analytic":
            raise SystemExit(f"{cond.name}: the bilinear model needs renderer.fog_model=analytic")
        parts[cond.name] = {f"c{u}{h}": renderer.render_linear(descriptor, cond, sunset=corner(cond, renderer.night, u, h))[0]
                            for u in (0, 1) for h in (0, 1)}
    return parts


def model(part: dict, u: float, haze: float) -> np.ndarray:
    """The scene-referred image at (u, haze), bilinear in the four corner renders."""
    a = part["c00"] + u * (part["c10"] - part["c00"])
    b = part["c01"] + u * (part["c11"] - part["c01"])
    return a + haze * (b - a)


def develop_all(renderer, scenes: list[dict], grid, light: SunsetLight) -> list[dict[str, np.ndarray]]:
    """The 8-bit images of every scene and condition under `light`, developed in one call per exposure."""
    return develop_linear(
        renderer, scenes, grid,
        lambda part, cond: model(part, 1.0 + (light.overcast - 1.0) * weight(cond, renderer.night), light.haze),
        lambda cond: lighting(cond, renderer.night, light)["light_level"])


def evaluate(images, labels, grid, settings, gta, chosen: dict[str, list[int]], rain_margin: float,
             band_margin: float) -> tuple[dict, list[str]]:
    """The experiment's checks and the sunset margins on every set; the Sunset-FOGGY medians and the distance to
    GTA V on all scenes. Returns (result, what failed: one line per check and set)."""
    sky = CLASS_NAMES.index("sky")
    reference = grid.reference
    conditions = {c.name: c for c in grid.conditions}
    order = [reference, *[n for n in grid.names if n != reference]]
    rows = group_rows(((i, images[i], labels[i]) for i in range(len(images))), reference, sky)
    failed: list[str] = []
    rain_gap, inside = -1.0, 1.0  # the worst set's: Sunset-RAIN minus Sunset-EXTRASUNNY luma; depth inside the bands
    (flo, fhi), (clo, chi) = (settings["bands"]["Sunset-FOGGY"][k] for k in ("luma_ratio", "contrast_ratio"))
    for name, idx in chosen.items():
        summary = summarise([r for r in rows if r["group_id"] in set(idx)], order)
        checks = band_checks(summary, settings["bands"]) + physics_checks(
            summary, conditions, reference, float(settings["night_max_luma_ratio"]), float(settings["night_sky_max_luma"]))
        failed += [f"{name}: {c['check']} ({c['value']})" for c in checks if not c["ok"]]
        by = {r["condition"]: r for r in summary}
        gap = by["Sunset-RAIN"]["luma_median"] - by["Sunset-EXTRASUNNY"]["luma_median"]
        fog = by["Sunset-FOGGY"]
        depth = min(fog["luma_ratio_median"] - flo, fhi - fog["luma_ratio_median"],
                    fog["contrast_ratio_median"] - clo, chi - fog["contrast_ratio_median"])
        rain_gap, inside = max(rain_gap, gap), min(inside, depth)
        if gap > -rain_margin:
            failed.append(f"{name}: Sunset-RAIN luma {gap:+.4f} of Sunset-EXTRASUNNY's (margin {rain_margin})")
        if depth < band_margin:
            failed.append(f"{name}: Sunset-FOGGY {depth:.3f} inside its bands (margin {band_margin})")
    by = {r["condition"]: r for r in summarise(rows, order)}
    luma, contrast = by["Sunset-FOGGY"]["luma_ratio_median"], by["Sunset-FOGGY"]["contrast_ratio_median"]
    result = {"foggy_luma": luma, "foggy_contrast": contrast, "rain_luma": by["Sunset-RAIN"]["luma_ratio_median"],
              "clear_luma": by["Sunset-EXTRASUNNY"]["luma_ratio_median"], "worst_rain_gap": rain_gap,
              "worst_band_depth": inside, "failed": len(failed),
              "error": math.log(luma / gta["luma"]) ** 2 + math.log(contrast / gta["contrast"]) ** 2}
    return result, failed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    scene_arguments(ap)
    ap.add_argument("--rain-margin", type=float, default=0.01,
                    help="Sunset-RAIN's median luma at least this under Sunset-EXTRASUNNY's on every set")
    ap.add_argument("--band-margin", type=float, default=0.05,
                    help="Sunset-FOGGY's median luma and contrast ratios at least this inside their bands on every set")
    ap.add_argument("--tolerance", type=float, default=0.005,
                    help="feasible points within this of the least error are as near GTA V: the least change wins")
    ap.add_argument("--overcast", type=float, nargs="+", default=[round(0.1 + 0.05 * i, 2) for i in range(19)])
    ap.add_argument("--haze", type=float, nargs="+", default=[round(0.6 + 0.1 * i, 2) for i in range(20)])
    args = run_arguments(ap, "fit_sunset_light")
    base, cfg, settings, grid, gta = setup(args, "Sunset-FOGGY")

    t0 = time.perf_counter()
    # the renders, kept for a rerun with another grid: named by what decides them (the fitted sunset does not)
    renderer_cfg = {k: v for k, v in cfg["renderer"].items() if k != "sunset"}
    what = {"seeds": args.seeds, "scenes": args.scenes, "renderer": renderer_cfg, "grid": grid.names,
            "blender": renderer_versions("blender"), "generate": VERSION, "fit": "sunset-2",
            "code": [sha256_file(f) for f in sorted(BACKEND.glob("*.py"))]}
    with build_renderer(cfg["renderer"]) as renderer:
        scenes, labels, descriptors = cached_renders(renderer, args.out, what, args.seeds, args.scenes, base, grid, t0,
                                                      render_parts)

        chosen = sets(args.seeds, args.scenes, args.subset)
        points = []
        for values in itertools.product(args.overcast, args.haze):
            light = SunsetLight(*values)
            images = develop_all(renderer, scenes, grid, light)
            result, failed = evaluate(images, labels, grid, settings, gta, chosen, args.rain_margin, args.band_margin)
            points.append({**dict(zip(TERMS, values)), **result, "feasible": not failed,
                           "first_failure": failed[0] if failed else ""})
            print(f"{light}: Sunset-FOGGY luma {result['foggy_luma']:.3f} contrast {result['foggy_contrast']:.3f}, "
                  f"Sunset-RAIN luma {result['rain_luma']:.3f} (clear {result['clear_luma']:.3f}; worst set "
                  f"{result['worst_rain_gap']:+.4f}), error {result['error']:.3f}, {result['failed']} failed",
                  flush=True)
        table = pd.DataFrame(points)
        args.out.mkdir(parents=True, exist_ok=True)
        table.to_csv(args.out / "fit.csv", index=False, float_format="%.4f")
        feasible = table[table["feasible"]].copy()
        if feasible.empty:
            print(f"no point passes every check on every set with the margins; widen the grid ({args.out / 'fit.csv'})")
            raise SystemExit(1)
        # as near GTA V as the least error, within --tolerance: of those, the least change from the sky model's
        feasible["change"] = np.log(feasible["overcast"]) ** 2 + np.log(feasible["haze"]) ** 2
        near = feasible[feasible["error"] <= feasible["error"].min() + args.tolerance]
        best = near.sort_values(["change", "error"]).iloc[0]
        light = SunsetLight(**{t: float(best[t]) for t in TERMS})
        images = develop_all(renderer, scenes, grid, light)
        rows = []
        for name, idx in chosen.items():
            result, failed = evaluate([images[i] for i in idx], [labels[i] for i in idx], grid, settings, gta,
                                      {name: list(range(len(idx)))}, args.rain_margin, args.band_margin)
            rows.append({"set": name, "rain_luma_ratio": result["rain_luma"], "clear_luma_ratio": result["clear_luma"],
                         "rain_minus_clear_luma": result["worst_rain_gap"], "foggy_luma_ratio": result["foggy_luma"],
                         "foggy_contrast_ratio": result["foggy_contrast"], "failed": "; ".join(failed)})
        pd.DataFrame(rows).to_csv(args.out / "checks.csv", index=False, float_format="%.4f")
        print(pd.DataFrame(rows).to_string(index=False, float_format="%.3f"))
        if args.verify:
            verify(renderer, scenes, descriptors, grid, light)
    print(f"\n{len(points)} points ({len(feasible)} feasible, {len(near)} within {args.tolerance} of the least error "
          f"{feasible['error'].min():.4f}), {time.perf_counter() - t0:.0f} s; chosen (error {best['error']:.4f}; "
          "pairedgta/conf/renderer/blender.yaml):")
    print("sunset:\n" + "".join(f"  {t}: {getattr(light, t):g}\n" for t in TERMS), end="")


def verify(renderer, scenes, descriptors, grid, light: SunsetLight) -> None:
    """The model against a real render of the chosen point: mean absolute difference in grey levels, on the first
    two scenes."""
    saved, renderer.sunset = renderer.sunset, light
    try:
        modelled = develop_all(renderer, scenes[:2], grid, light)
        for i in range(min(2, len(scenes))):
            for name in ("Sunset-RAIN", "Sunset-FOGGY"):
                real = renderer.render(descriptors[i], grid[name]).image
                diff = np.abs(real.astype(int) - modelled[i][name].astype(int)).mean()
                print(f"verify scene {i} {name}: model vs render {diff:.2f} grey levels")
    finally:
        renderer.sunset = saved


if __name__ == "__main__":
    main()
