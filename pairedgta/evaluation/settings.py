"""The metric settings an evaluation is computed and hashed under (the `metric` node of evaluate's hash) and the
conditions it covers. The keys are typed and checked once (pairedgta/schema.py); what is left here needs the
dataset's grid."""
from __future__ import annotations

from typing import Any

from pairedgta.cityscapes import NUM_CLASSES, class_id
from pairedgta.conditions import ConditionGrid
from pairedgta.errors import ConfigError
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.schema import EvaluateConfig, RunConfig, as_dict


def conditions_for(ev: EvaluateConfig, grid: ConditionGrid) -> list[str]:
    """The conditions an evaluation covers: `evaluate.conditions` (always with the reference), else all."""
    if not ev.conditions:
        return list(grid.names)
    unknown = [c for c in ev.conditions if c not in grid.names]
    if unknown:  # a dataset's own grid (ACDC) may lack a name the run's grid has
        raise ConfigError(f"evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(grid.names)}")
    return [c for c in grid.names if c in ev.conditions or c == grid.reference]


def metric_settings(run: RunConfig, grid_names: list[str], reference: str) -> dict[str, Any]:
    """Every `metric.*` and `evaluate.sampling*` value the numbers depend on: the node evaluate hashes, so a
    setting that changes a number changes the cache key."""
    metric, rho, boot = run.metric, run.metric.rho, run.metric.bootstrap
    clean = rho.clean_condition or reference
    if clean not in grid_names:
        raise ConfigError(f"metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(grid_names)}")
    selections = list(rho.selections)
    return {
        "tau_mass": metric.tau_mass, "m": rho.m, "min_transmittance": metric.min_transmittance,
        "selections": selections,
        "class_ids": list(range(NUM_CLASSES)) if not rho.classes else [class_id(c) for c in rho.classes],
        "reference_mode": metric.reference,
        "resamples": boot.resamples, "confidence": boot.confidence, "seed": boot.seed, "clean": clean,
        "convention": convention_from_config(as_dict(metric), selections).as_dict(),
        "sampling": run.evaluate.sampling,
        # only a random draw depends on the seed (so `seed=` alone does not invalidate sampling=all results)
        "sampling_seed": run.evaluate.sampling_seed if run.evaluate.sampling == "random_one" else 0,
    }
