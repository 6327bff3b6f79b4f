"""Photometry of paired images: how much darker, flatter and tinted a condition makes the same scene.

The statistic is the one measured on the authors' GTA V frames (`pairedgta/data/gta_photometry.md`): mean
Rec. 709 luma of the sRGB-encoded image (0-1), RMS contrast (population std of that luma) and mean R, G, B;
per group the adverse image over its clean image; per condition the median (and range) over groups. A
ratio, not an absolute level, because the clean images of two renderers differ in content, not only light.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

REC709 = np.array([0.2126, 0.7152, 0.0722])


def image_stats(image: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Mean luma, RMS contrast and mean R, G, B of an 8-bit (or 0-1 float) RGB image, over `mask` if given."""
    x = np.asarray(image, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] < 3:
        raise ValueError(f"expected an H x W x 3 image, got shape {x.shape}")
    if np.asarray(image).dtype == np.uint8:
        x = x / 255.0
    x = x[..., :3]
    y = x @ REC709
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if not m.any():
            return {"luma": float("nan"), "contrast": float("nan"), "r": float("nan"), "g": float("nan"),
                    "b": float("nan")}
        y, x = y[m], x[m]
    else:
        x = x.reshape(-1, 3)
    mean = x.mean(axis=0)
    return {"luma": float(y.mean()), "contrast": float(y.std()), "r": float(mean[0]), "g": float(mean[1]),
            "b": float(mean[2])}


def group_rows(groups: Iterable[tuple[str, Mapping[str, np.ndarray], np.ndarray | None]], reference: str,
               sky_class: int | None = None) -> list[dict[str, Any]]:
    """One row per (group, condition): the image's statistics, its ratios to the group's clean image and,
    where labels and `sky_class` are given, the mean luma of the sky."""
    rows: list[dict[str, Any]] = []
    for gid, images, labels in groups:
        if reference not in images:
            continue
        clean = image_stats(images[reference])
        sky = None if labels is None or sky_class is None else np.asarray(labels) == sky_class
        for name, image in images.items():
            s = image_stats(image)
            row = {"group_id": gid, "condition": name, **s,
                   "luma_ratio": s["luma"] / clean["luma"] if clean["luma"] > 0 else float("nan"),
                   "contrast_ratio": s["contrast"] / clean["contrast"] if clean["contrast"] > 0 else float("nan"),
                   "sky_luma": image_stats(image, sky)["luma"] if sky is not None else float("nan")}
            rows.append(row)
    return rows


def summarise(rows: list[dict[str, Any]], order: list[str]) -> list[dict[str, Any]]:
    """Per condition: median, min and max over groups of the ratios; medians of the levels."""
    out = []
    for name in order:
        sel = [r for r in rows if r["condition"] == name]
        if not sel:
            continue

        def col(key: str) -> np.ndarray:
            v = np.array([r[key] for r in sel], dtype=float)
            return v[np.isfinite(v)]

        row: dict[str, Any] = {"condition": name, "n_groups": len(sel)}
        for key in ("luma_ratio", "contrast_ratio"):
            v = col(key)
            row[f"{key}_median"] = float(np.median(v)) if v.size else float("nan")
            row[f"{key}_min"] = float(v.min()) if v.size else float("nan")
            row[f"{key}_max"] = float(v.max()) if v.size else float("nan")
        for key in ("luma", "contrast", "r", "g", "b", "sky_luma"):
            v = col(key)
            row[f"{key}_median"] = float(np.median(v)) if v.size else float("nan")
        out.append(row)
    return out


def physics_checks(summary: list[dict[str, Any]], conditions: Mapping[str, Any], reference: str,
                   night_max_luma_ratio: float = 0.35, night_sky_max_luma: float = 0.15) -> list[dict[str, Any]]:
    """What a condition's name promises, for conditions without a GTA V frame to compare with: a night
    keeps at most `night_max_luma_ratio` of the clean luma and a sky darker than `night_sky_max_luma`; rain
    is no brighter than its time's clear sky; for each weather, day > sunset > night in mean luma.
    `conditions` maps names to objects with `time` and `weather`. One row per check: what, value, ok."""
    by = {r["condition"]: r for r in summary}
    checks: list[dict[str, Any]] = []

    def add(check: str, value: float, ok: bool) -> None:
        checks.append({"check": check, "value": round(float(value), 4), "ok": bool(ok)})

    for name, r in by.items():
        c = conditions.get(name)
        if c is None or name == reference:
            continue
        if c.time == "Night":
            add(f"{name}: luma ratio <= {night_max_luma_ratio}", r["luma_ratio_median"],
                r["luma_ratio_median"] <= night_max_luma_ratio)
            if np.isfinite(r["sky_luma_median"]):
                add(f"{name}: sky luma < {night_sky_max_luma}", r["sky_luma_median"], r["sky_luma_median"] < night_sky_max_luma)
        if c.weather == "RAIN":
            clear = next((n for n, o in conditions.items() if o.time == c.time and o.weather == "EXTRASUNNY"), None)
            if clear in by:
                add(f"{name}: luma <= {clear}", r["luma_median"] - by[clear]["luma_median"],
                    r["luma_median"] <= by[clear]["luma_median"])
    weathers = sorted({c.weather for c in conditions.values()})
    for w in weathers:
        names = [next((n for n, o in conditions.items() if o.time == t and o.weather == w), None)
                 for t in ("Day", "Sunset", "Night")]
        if all(n in by for n in names):
            lum = [by[n]["luma_median"] for n in names]
            add(f"{w}: luma Day > Sunset > Night", min(lum[0] - lum[1], lum[1] - lum[2]), lum[0] > lum[1] > lum[2])
    return checks


def ladder_checks(summary: list[dict[str, Any]], order: list[str], max_rise: float = 0.02,
                  plateau_max: float = 0.35) -> list[dict[str, Any]]:
    """A light ladder (`order`: the clean image, then darker steps): mean luma ratio falls step by step, no
    rise above `max_rise`, down to a last step at most `plateau_max` of the clean image."""
    by = {r["condition"]: r["luma_ratio_median"] for r in summary}
    steps = [n for n in order if n in by]
    if len(steps) < 2:
        return []
    rise = max(b - a for a, b in zip([by[n] for n in steps[:-1]], [by[n] for n in steps[1:]]))
    return [{"check": f"ladder: luma ratio falls step by step (largest rise {max_rise} at most)", "value": round(rise, 4),
             "ok": bool(rise <= max_rise)},
            {"check": f"ladder: last step {steps[-1]} <= {plateau_max} of the clean luma", "value": round(by[steps[-1]], 4),
             "ok": bool(by[steps[-1]] <= plateau_max)}]


def band_checks(summary: list[dict[str, Any]], bands: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The calibration bands: `bands[condition][stat] = [lo, hi]` for stat luma_ratio / contrast_ratio
    (medians over groups)."""
    by = {r["condition"]: r for r in summary}
    checks = []
    for name, stats in bands.items():
        if name not in by:
            continue
        for stat, (lo, hi) in stats.items():
            v = by[name][f"{stat}_median"]
            checks.append({"check": f"{name}: {stat} in [{lo}, {hi}] (GTA V band)", "value": round(float(v), 4),
                           "ok": bool(lo <= v <= hi)})
    return checks


__all__ = ["REC709", "band_checks", "group_rows", "image_stats", "ladder_checks", "physics_checks", "summarise"]
