"""The run: plan it, open each pass's dataset, then pseudo-label, evaluate every model and plot, each
stage cached by config hash (pairedgta.stages.planning says what and over which data), logged to MLflow."""
from __future__ import annotations

import logging
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pairedgta.cache import StageCache
from pairedgta.config_checks import check_run_config
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.stages import evaluate, planning, plot, pseudolabel
from pairedgta.tracking import Tracker

log = logging.getLogger("pairedgta")


def run(cfg: DictConfig, task_overrides: list[str] | None = None) -> dict[str, Any]:
    """`task_overrides`: the command line's overrides (Hydra's), to know whether `model=` was chosen."""
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    check_run_config(container)
    planning.check_roots(container)
    plan = planning.make_plan(container)
    models = planning.run_models(container, planning.model_group_overridden(task_overrides))
    pseudolabel.check_tau(container)
    cache = StageCache(container["cache_dir"])
    tracking = container.get("tracking") or {}
    tracker = Tracker(tracking.get("uri", "sqlite:///outputs/mlflow.db"),
                      str(tracking.get("experiment_name") or container.get("name", "default")), bool(tracking.get("enabled", True)))
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"dataset": None, "evaluate": {}, "plot": None, "stages": results.setdefault("stages", [])}

    if plan.check_models:  # Cityscapes val: a check of the models themselves, not a paired run
        from pairedgta.stages import cityscapes_val

        ctx = planning.pass_context(container, cache, plan, results)
        with tracker.run(str(container.get("name", "run"))):
            tracker.params({k: v for k, v in container.items() if k != "hydra"})
            return cityscapes_val.run(ctx, models.evaluated, tracker)

    passes = []
    configs = planning.pass_configs(container)
    for label, pcfg in configs:
        ctx = planning.pass_context(pcfg, cache, plan, results)
        p = planning.open_pass(label, ctx, plan, results)
        passes.append((ctx, p))
        if p.dataset is not None:
            log.info("dataset %s%s: %d groups, reference %s", p.dataset.name, f" ({label})" if len(configs) > 1 else "",
                     len(p.dataset), p.dataset.reference)
            summary["dataset"] = summary["dataset"] or str(p.dataset.root)
    if "generate" in results:
        summary["generate"] = str(results["generate"].path)
    if not (plan.run_pseudo or plan.plotting):
        return summary
    with tracker.run(str(container.get("name", "run"))):
        tracker.params({k: v for k, v in container.items() if k != "hydra"})
        tracker.tags({"dataset": passes[0][1].dataset.name if passes[0][1].dataset else "none",
                      "dataset_key": str(passes[0][1].dataset_key), "passes": ", ".join(p.label for _, p in passes)})
        for ctx, p in passes:
            if p.dataset is not None and plan.run_pseudo:
                _data_stages(ctx, p, plan, models, tracker, summary, multi=len(passes) > 1)
        if plan.plotting:
            figures = plot.run(passes[0][0], [p for _, p in passes])
            summary["plot"] = str(figures.path)
            tracker.artifacts(figures.files(), "figures")
            tracker.metrics(figures.metrics())
    return summary


def _data_stages(ctx: Any, p: planning.PassResult, plan: planning.Plan, models: planning.RunModels, tracker: Tracker,
                 summary: dict[str, Any], multi: bool) -> None:
    """Pseudo-labels, then every model's evaluation (a nested MLflow run each) of one pass."""
    assert p.dataset is not None and p.dataset_key is not None
    p.pseudo = pseudolabel.run(ctx, p.dataset, p.dataset_key, models.reference)
    summary.setdefault("pseudolabel", str(p.pseudo.path))
    tracker.artifacts(p.pseudo.artifacts(), f"pseudolabel/{p.label}" if multi else "pseudolabel")
    if not plan.run_eval:
        return
    collect = plan.plotting and bool((ctx.cfg.get("plot") or {}).get("collect_cached"))
    for model_cfg in models.evaluated:
        name = f"{p.label}/{model_cfg['name']}" if multi else model_cfg["name"]
        try:
            result = evaluate.run(ctx, p.dataset, p.dataset_key, p.pseudo, model_cfg)
        except PairedGTAError as exc:
            if collect and "evaluate" not in plan.stages and "no cached output" in str(exc):
                log.info("evaluate [%s]: not cached; plot collects the cached models only", model_cfg["name"])
                continue
            raise
        if not result.complete:  # a shard job: its partial sums wait for the other shards
            if plan.plotting:
                raise ConfigError("evaluate.shard is set and other shards' groups are still missing: run the remaining "
                                  "shards, then plot without evaluate.shard/num_shards")
            continue
        p.evaluations.append(result)
        with tracker.run(name, nested=True):
            tracker.params({"model": model_cfg, "metric": ctx.cfg["metric"], "reference_model": models.reference["name"]})
            tracker.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit), "dataset": p.dataset.name, "pass": p.label})
            tracker.metrics(result.metrics())
            tracker.artifacts(result.artifacts(), "evaluate")
        summary["evaluate"][name] = str(result.path)
    if collect:
        extra = planning.collect_cached(ctx, p)
        if extra:
            log.info("plot: collected %d cached evaluation(s) of this dataset: %s", len(extra),
                     ", ".join(e.model for e in extra))
            p.evaluations.extend(extra)
    if plan.plotting and "evaluate" in plan.needs and not p.evaluations:
        raise ConfigError(f"plot: no evaluation of dataset {p.label} to draw; run it first, e.g. stages=[evaluate,plot]")
