"""Michaelis et al. 2019's robustness scores (bethgelab/robust-detection-benchmark): P, the clean performance; mPC,
the mean performance over the corruptions -- here the adverse conditions (the paper's eight, or a ladder's steps);
rPC = mPC / P, a ratio of means as for COCO and Cityscapes. Undefined (NaN) where P is undefined or under
`min_clean` (a model that finds next to nothing on the clean image has no robustness to speak of: 0.001 / 0.001
would read as perfect)."""
from __future__ import annotations

import math
from typing import Mapping, Sequence


MIN_CLEAN_AP = 0.05


def corruption_scores(performance: Mapping[str, float], clean: str, adverse: Sequence[str],
                      min_clean: float = MIN_CLEAN_AP) -> dict[str, float]:
    p = float(performance.get(clean, math.nan))
    values = [float(performance.get(c, math.nan)) for c in adverse]
    values = [v for v in values if math.isfinite(v)]
    mpc = sum(values) / len(values) if values and len(values) == len(adverse) else math.nan
    rpc = mpc / p if math.isfinite(p) and p >= min_clean and p > 0 and math.isfinite(mpc) else math.nan
    return {"P": p, "mPC": mpc, "rPC": rpc}


def subsets(adverse: Sequence[str], clean: str) -> dict[str, list[str]]:
    """The adverse conditions pooled, and per part of their names (time of day, weather: Night-*, *-RAIN) where
    the grid's names have parts: the rPC of the night alone, of rain alone."""
    out = {"all adverse": list(adverse)}
    parts: dict[str, list[str]] = {}
    for c in [clean, *adverse]:
        if "-" in c:
            time, weather = c.split("-", 1)
            parts.setdefault(f"{time}-*", []).append(c)
            parts.setdefault(f"*-{weather}", []).append(c)
    for name, conds in parts.items():
        conds = [c for c in conds if c != clean]
        if 0 < len(conds) < len(adverse):
            out[name] = conds
    return out


__all__ = ["MIN_CLEAN_AP", "corruption_scores", "subsets"]
