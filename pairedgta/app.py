"""The run: plan it, open each pass's dataset, then pseudo-label, evaluate every model and plot, each
stage cached by config hash (pairedgta.stages.planning says what and over which data), logged to MLflow:
a parent run with the invocation's config and the shared figures, a nested run per model and dataset
with its metrics, xi table, dataset, config and its own figures. Each model is loaded once per run."""
from __future__ import annotations

import logging
from contextlib import closing
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pairedgta.cache import StageCache
from pairedgta.config_checks import check_run_config
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.models import run_models as loaded_once
from pairedgta.stages import evaluate, planning, plot, pseudolabel
from pairedgta.tracking import Tracker, bundle, class_metrics, dataset_label, run_name, xi_table
from pairedgta.tracking_worker import open_tracker

log = logging.getLogger("pairedgta")


def run(cfg: DictConfig, task_overrides: list[str] | None = None) -> dict[str, Any]:
    """`task_overrides`: the command line's overrides (Hydra's), to know whether `model=` was chosen."""
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    check_run_config(container)
    planning.check_roots(container)
    plan = planning.make_plan(container)
    models = plan.models = planning.run_models(container, planning.model_group_overridden(task_overrides))
    pseudolabel.check_tau(container)
    cache = StageCache(container["cache_dir"], str((container.get("cache") or {}).get("verify", "stat")))
    tracker = open_tracker(container)  # MLflow is a record: a failing store costs one warning, not the run
    model_names = [m["name"] for m in models.evaluated] if plan.run_pseudo or plan.check_models else []
    with loaded_once(), closing(tracker):  # closed: a background tracker has logged everything
        summary = _run(container, plan, models, cache, tracker, tracker.experiment, model_names)
    return {**summary, "mlflow": tracker.ui_link()}


def _log_invocation(tracker: Tracker, container: dict[str, Any]) -> None:
    tracker.params(config := {k: v for k, v in container.items() if k != "hydra"})
    tracker.config(config)
    tracker.hydra_config()


def _run(container: dict[str, Any], plan: planning.Plan, models: planning.RunModels, cache: StageCache,
         tracker: Tracker, experiment: str, model_names: list[str]) -> dict[str, Any]:
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"dataset": None, "evaluate": {}, "plot": None, "stages": results.setdefault("stages", [])}

    if plan.check_models:  # Cityscapes val: a check of the models themselves, not a paired run
        from pairedgta.stages import cityscapes_val

        ctx = planning.pass_context(container, cache, plan, results)
        with tracker.run(run_name(experiment, model_names, [str(container["dataset"].get("name"))])):
            _log_invocation(tracker, container)
            return cityscapes_val.run(ctx, models.evaluated, tracker)

    passes, configs = [], planning.pass_configs(container)  # the run opens before generation: a stop there is recorded
    with tracker.run(run_name(experiment, model_names, [str(c.get("dataset", {}).get("name")) for _, c in configs])):
        _log_invocation(tracker, container)
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
        tracker.rename(run_name(experiment, model_names, [dataset_label(p.dataset.name, p.dataset_key) for _, p in passes
                                                           if p.dataset is not None]))
        tracker.tags({"dataset": passes[0][1].dataset.name if passes[0][1].dataset else "none",
                      "dataset_key": str(passes[0][1].dataset_key), "passes": ", ".join(p.label for _, p in passes),
                      "models": ", ".join(model_names)})
        if not (plan.run_pseudo or plan.plotting):
            return summary
        model_runs: list[tuple[str | None, str, str]] = []  # (nested run, model, pass) for the figures
        for ctx, p in ((c, q) for c, q in passes if q.dataset is not None and plan.run_pseudo):
            with p.reading():  # a blank or converted image: one warning for the dataset, when its stages are done
                _log_dataset(tracker, p)
                model_runs += _data_stages(ctx, p, plan, models, tracker, summary, experiment, multi=len(passes) > 1)
        if plan.plotting:
            figures = plot.run(passes[0][0], [p for _, p in passes])
            summary["plot"] = str(figures.path)
            own_runs = {(model, label) for _, model, label in model_runs}
            tracker.stage_files(bundle("plot", figures.key), figures.hit, figures.files_except(own_runs), "figures")
            tracker.metrics(figures.metrics())
            for run_id, model, label in model_runs:  # each model's own figures into its nested run
                with tracker.run(run_id=run_id, nested=True):
                    tracker.stage_files(bundle("plot", figures.key, label, model), figures.hit,
                                        figures.files_of(model, label), "figures")
    return summary


def _log_dataset(tracker: Tracker, p: planning.PassResult) -> None:
    assert p.dataset is not None
    tracker.dataset(p.dataset.name, p.dataset.root, str(p.dataset_key).split(":", 1)[-1],
                    {"pass": p.label, "dataset_key": str(p.dataset_key), "reference": p.dataset.reference})


def _data_stages(ctx: Any, p: planning.PassResult, plan: planning.Plan, models: planning.RunModels, tracker: Tracker,
                 summary: dict[str, Any], experiment: str, multi: bool) -> list[tuple[str | None, str, str]]:
    """Pseudo-labels, then every model's evaluation (a nested MLflow run each) of one pass."""
    assert p.dataset is not None and p.dataset_key is not None
    p.pseudo = pseudolabel.run(ctx, p.dataset, p.dataset_key, models.reference)
    summary.setdefault("pseudolabel", str(p.pseudo.path))
    tracker.stage_files(bundle("pseudolabel", p.pseudo.key), p.pseudo.hit, p.pseudo.artifacts(),
                        f"pseudolabel/{p.label}" if multi else "pseudolabel")
    runs: list[tuple[str | None, str, str]] = []
    if not plan.run_eval:
        return runs
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
        with tracker.run(run_name(experiment, [model_cfg["name"]], [dataset_label(p.dataset.name, p.dataset_key)]), nested=True):
            tracker.params({"model": model_cfg, "metric": ctx.cfg["metric"], "reference_model": models.reference["name"]})
            tracker.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit), "dataset": p.dataset.name, "pass": p.label,
                          "model": model_cfg["name"]})
            tracker.metrics(result.metrics(per_class=class_metrics(ctx.cfg), cfg=ctx.cfg))
            _log_dataset(tracker, p)
            tracker.config({**{k: v for k, v in ctx.cfg.items() if k not in ("hydra", "variants")}, "model": model_cfg})
            tracker.stage_files(bundle("evaluate", result.key), result.hit, result.artifacts(), "evaluate",
                                tables={"xi_table.json": xi_table(result.xi())})
            runs.append((tracker.run_id(), model_cfg["name"], p.label))
        summary["evaluate"][name] = str(result.path)
    if collect:
        extra = planning.collect_cached(ctx, p)
        if extra:
            log.info("plot: collected %d cached evaluation(s) of this dataset: %s", len(extra),
                     ", ".join(e.model for e in extra))
            p.evaluations.extend(extra)
    if plan.plotting and "evaluate" in plan.needs and not p.evaluations:
        raise ConfigError(f"plot: no evaluation of dataset {p.label} to draw; run it first, e.g. stages=[evaluate,plot]")
    return runs
