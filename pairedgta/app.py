"""The stage graph: generate -> pseudolabel -> evaluate -> plot, each cached by config hash."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pairedgta.cache import StageCache
from pairedgta.conditions import build_condition_grid
from pairedgta.datasets import open_dataset
from pairedgta.errors import ConfigError
from pairedgta.models import model_config
from pairedgta.stages import evaluate, generate, plot, pseudolabel
from pairedgta.stages.common import STAGES, Context, StageResult
from pairedgta.tracking import Tracker, evaluation_metrics

log = logging.getLogger("pairedgta")


def _as_list(value: Any, key: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def check_config(cfg: dict[str, Any]) -> tuple[list[str], set[str]]:
    stages = _as_list(cfg.get("stages"), "stages")
    force = set(_as_list(cfg.get("force"), "force"))
    for key, values in (("stages", stages), ("force", force)):
        bad = [s for s in values if s not in STAGES]
        if bad:
            raise ConfigError(f"{key}={bad} names unknown stage(s); stages are {', '.join(STAGES)}")
    if cfg.get("device") not in ("cpu", "cuda", "auto") and not str(cfg.get("device")).startswith("cuda:"):
        raise ConfigError(f"device={cfg.get('device')!r}; use cpu, cuda or auto")
    return stages, force


def evaluated_models(cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """`models=[a,b]` wins over the single `model` group; the device comes from the top-level key."""
    names = cfg.get("models")
    if names:
        return [model_config(str(n), device=cfg["device"]) for n in _as_list(names, "models")]
    model = dict(cfg["model"])
    model["device"] = cfg["device"]
    return [model]


def run(cfg: DictConfig) -> dict[str, Any]:
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    if OmegaConf.is_missing(cfg.dataset, "root"):
        raise ConfigError(f"dataset.root is required for dataset={cfg.dataset.name}; set dataset.root=PATH")
    stages, force = check_config(container)
    grid = build_condition_grid(container["conditions"])
    cache = StageCache(container["cache_dir"])
    ctx = Context(cfg=container, grid=grid, cache=cache, stages=stages, force=force)
    models = evaluated_models(container)
    tracking = container.get("tracking") or {}
    tracker = Tracker(tracking.get("uri", "sqlite:///outputs/mlflow.db"), str(tracking.get("experiment_name") or container.get("name", "default")), bool(tracking.get("enabled", True)))

    dcfg = container["dataset"]
    if dcfg.get("kind") == "cityscapes":
        # a sanity check of the models themselves (wrong preprocessing shows up here), not a paired run
        from pairedgta.stages import cityscapes_val

        with tracker.run(str(container.get("name", "run"))):
            tracker.params({k: v for k, v in container.items() if k not in ("hydra",)})
            return cityscapes_val.run(ctx, models, tracker)

    # dataset: the generate stage's output, or an existing root
    if dcfg.get("kind") == "generated" and not dcfg.get("root"):
        gen = generate.run(ctx)
        dataset = open_dataset(dcfg, grid, root=gen.path)
        dataset_key = f"generate:{gen.key}"
        ctx.results["generate"] = gen
    else:
        if "generate" in stages:
            log.info("generate: skipped, dataset.root=%s is an existing dataset", dcfg.get("root"))
        dataset = open_dataset(dcfg, grid)
        dataset_key = f"external:{dataset.fingerprint()}"
    log.info("dataset %s: %d groups, reference %s", dataset.name, len(dataset), dataset.reference)
    needs_eval = any(s in stages for s in ("pseudolabel", "evaluate", "plot"))
    summary: dict[str, Any] = {"dataset": str(dataset.root), "evaluate": {}, "plot": None, "stages": ctx.results.setdefault("stages", [])}
    if not needs_eval:
        return summary
    with tracker.run(str(container.get("name", "run"))):
        tracker.params({k: v for k, v in container.items() if k not in ("hydra",)})
        tracker.tags({"dataset": dataset.name, "dataset_key": dataset_key})
        pseudo = pseudolabel.run(ctx, dataset, dataset_key)
        summary["pseudolabel"] = str(pseudo.path)
        tracker.artifacts([pseudo.path / "histogram.csv", pseudo.path / "quality.csv"], "pseudolabel")
        if not any(s in stages for s in ("evaluate", "plot")):
            return summary
        evaluations: list[StageResult] = []
        for model_cfg in models:
            with tracker.run(model_cfg["name"], nested=True):
                result = evaluate.run(ctx, dataset, dataset_key, pseudo, model_cfg)
                evaluations.append(result)
                tracker.params({"model": model_cfg, "metric": container["metric"], "reference_model": container["reference_model"]})
                tracker.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit)})
                tracker.metrics(evaluation_metrics(result.path))
                tracker.artifacts(sorted(result.path.glob("*.csv")) + [result.path / "summary.json"], "evaluate")
            summary["evaluate"][model_cfg["name"]] = str(result.path)
        if "plot" in stages:
            figures = plot.run(ctx, evaluations)
            summary["plot"] = str(figures.path)
            tracker.artifacts(sorted(p for p in figures.path.iterdir() if p.suffix in (".png", ".pdf", ".csv")), "figures")
    return summary
