"""The metric settings an evaluation is computed and hashed under (the `metric` node of evaluate's hash)
and the conditions it covers, each checked with a one-line error naming the key."""
from __future__ import annotations

from typing import Any

from pairedgta.cityscapes import NUM_CLASSES, class_id
from pairedgta.conditions import ConditionGrid
from pairedgta.errors import ConfigError
from pairedgta.evaluation.inputs import SAMPLINGS
from pairedgta.metrics import SELECTIONS
from pairedgta.metrics.conventions import convention_from_config


def conditions_for(cfg: dict[str, Any], grid: ConditionGrid) -> list[str]:
    """The conditions an evaluation covers: `evaluate.conditions` (always with the reference), else all."""
    wanted = (cfg.get("evaluate") or {}).get("conditions")
    if not wanted:
        return list(grid.names)
    unknown = [c for c in wanted if c not in grid.names]
    if unknown:
        raise ConfigError(f"evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(grid.names)}")
    return [c for c in grid.names if c in wanted or c == grid.reference]


def metric_settings(cfg: dict[str, Any], grid_names: list[str], reference: str) -> dict[str, Any]:
    """Every `metric.*` and `evaluate.sampling*` key the numbers depend on, checked and with its default:
    the node evaluate hashes, so a setting that changes a number changes the cache key."""
    metric = cfg["metric"]
    rho = metric.get("rho") or {}
    selections = list(rho.get("selections") or SELECTIONS)
    bad = [s for s in selections if s not in SELECTIONS]
    if bad:
        raise ConfigError(f"metric.rho.selections: unknown {bad}; use {list(SELECTIONS)}")
    classes = rho.get("classes")
    class_ids = list(range(NUM_CLASSES)) if not classes else [class_id(c) for c in classes]
    tau = float(metric.get("tau_mass", 0.9))
    if not 0.0 <= tau <= 1.0:
        raise ConfigError(f"metric.tau_mass={tau} must be in [0, 1]")
    m = int(rho.get("m", 25))
    if m < 1:
        raise ConfigError(f"metric.rho.m={m} must be >= 1")
    ref_mode = metric.get("reference", "both")
    if ref_mode not in ("pseudo_label", "ground_truth", "both"):
        raise ConfigError(f"metric.reference={ref_mode!r}; use pseudo_label, ground_truth or both")
    boot = metric.get("bootstrap") or {}
    clean = rho.get("clean_condition") or reference
    if clean not in grid_names:
        raise ConfigError(f"metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(grid_names)}")
    ev = cfg.get("evaluate") or {}
    sampling = str(ev.get("sampling") or "all")
    if sampling not in SAMPLINGS:
        raise ConfigError(f"evaluate.sampling={sampling!r}; use one of {', '.join(SAMPLINGS)}")
    min_t = float(metric.get("min_transmittance") or 0.0)
    if not 0.0 <= min_t < 1.0:
        raise ConfigError(f"metric.min_transmittance={min_t}; use a transmittance in [0, 1)")
    settings = {
        "tau_mass": tau, "m": m, "min_transmittance": min_t, "selections": selections, "class_ids": class_ids, "reference_mode": ref_mode,
        "resamples": int(boot.get("resamples", 1000)), "confidence": float(boot.get("confidence", 0.95)),
        "seed": int(boot.get("seed", 0)), "clean": clean,
        "convention": convention_from_config(metric, selections).as_dict(),
        "sampling": sampling,
        # only a random draw depends on the seed (so `seed=` alone does not invalidate sampling=all results)
        "sampling_seed": int(ev.get("sampling_seed") or 0) if sampling == "random_one" else 0,
    }
    return settings
