"""One colour per detector in every detection figure, from a palette that scales past 20 models: a hue per family
(FCOS blue, RetinaNet orange, Faster R-CNN green, further families further hues) and a lightness step per member
within it, so a reader tells the family at a glance and the legend names it. Without matplotlib (colorsys)."""
from __future__ import annotations

import colorsys
import functools
from typing import Iterable, Mapping

from pairedgta.figures.model_colors import MODEL_DISPLAY

FAMILY_HUES = {"fcos": 0.58, "retinanet": 0.07, "fasterrcnn": 0.33}  # blue, orange, green
EXTRA_HUES = (0.78, 0.95, 0.14, 0.48, 0.70, 0.02)  # purple, pink, olive, teal, ...: further families, in name order
FAMILY_DISPLAY = {"fcos": "FCOS", "retinanet": "RetinaNet", "fasterrcnn": "Faster R-CNN"}
LIGHTNESS = (0.24, 0.70)  # darkest and lightest member of a family: dark enough on white, light enough to differ


@functools.cache
def zoo_families() -> dict[str, str]:
    """Every detector the config tree names (`model=<name>`) and its family: a member's shade is its place among
    these, so it is the same in every figure whichever subset a figure draws."""
    from pairedgta.configs import group_option, group_options

    families = {n: group_option("model", n).get("family") for n in group_options("model")}
    return {n: f for n, f in families.items() if f in FAMILY_HUES}


def family_of(name: str) -> str:
    """The model config's `family`; a model without a config (a user's) is its own "other" family."""
    if name in zoo_families():
        return zoo_families()[name]
    from pairedgta.configs import group_option, group_options

    if name in group_options("model"):
        return str(group_option("model", name).get("family") or "other")
    return "other"


def detector_colors(names: Iterable[str], families: Mapping[str, str] | None = None) -> dict[str, str]:
    """Hex colour per detector in `names`: its family's hue, its shade its sorted place among the family's members
    (the config tree's and the given ones together). `families` overrides `family_of` (models without a config)."""
    names = list(dict.fromkeys(names))
    fam = {**zoo_families(), **{n: (families or {}).get(n) or family_of(n) for n in names}}
    extra = sorted({f for f in fam.values() if f not in FAMILY_HUES})
    hues = {**FAMILY_HUES, **{f: EXTRA_HUES[i % len(EXTRA_HUES)] for i, f in enumerate(extra)}}
    colors: dict[str, str] = {}
    for family in {fam[n] for n in names}:
        members = sorted(n for n, f in fam.items() if f == family)
        for n in names:
            if fam[n] == family:
                colors[n] = _shade(hues[family], members.index(n), len(members))
    return colors


def _shade(hue: float, i: int, n: int) -> str:
    # lightness evenly over the family's range; saturation alternates so neighbours differ in two ways
    light = LIGHTNESS[0] + (LIGHTNESS[1] - LIGHTNESS[0]) * (i / (n - 1) if n > 1 else 0.5)
    r, g, b = colorsys.hls_to_rgb(hue, light, 0.85 if i % 2 == 0 else 0.55)
    return "#{:02x}{:02x}{:02x}".format(round(r * 255), round(g * 255), round(b * 255))


def subject_shades(subject: str, population: Iterable[str]) -> tuple[str, str]:
    """A one-model panel's two series (e.g. its two worst conditions): its own colour and a lighter tint of it."""
    color = detector_colors([subject, *population])[subject]
    r, g, b = (int(color[k:k + 2], 16) / 255 for k in (1, 3, 5))
    h, light, sat = colorsys.rgb_to_hls(r, g, b)
    r, g, b = colorsys.hls_to_rgb(h, light + (0.88 - light) * 0.5, sat)
    return color, "#{:02x}{:02x}{:02x}".format(round(r * 255), round(g * 255), round(b * 255))


def detector_label(name: str, families: Mapping[str, str] | None = None) -> str:
    """The legend's entry: the model's name and its family, the family being what the hue says."""
    family = (families or {}).get(name) or family_of(name)
    return f"{MODEL_DISPLAY.get(name, name)} ({FAMILY_DISPLAY.get(family, family)})"


def detector_order(names: Iterable[str]) -> list[str]:
    """Legend order: by family, then by name, so a family's shades stand together."""
    return sorted(dict.fromkeys(names), key=lambda n: (family_of(n), n))


__all__ = ["FAMILY_DISPLAY", "detector_colors", "detector_label", "detector_order", "family_of", "subject_shades",
           "zoo_families"]
