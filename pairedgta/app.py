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
from pairedgta.models import run_models as loaded_once
from pairedgta.schema import RunConfig
from pairedgta.stages import evaluate, planning, plot, pseudolabel
from pairedgta.tracking import Recorder, dataset_label, open_tracker, run_name

log = logging.getLogger("pairedgta")
# The stages after a pass's dataset is open (generate opens it: planning.open_pass), in order: each module's
# `step(ctx, pass, state)` runs its pairedgta.stages.common.Stage units through the cache and records them.
PASS_STAGES = (pseudolabel, evaluate)
RUN_STAGES = (plot,)  # once over every pass: `step(ctx, passes, state)`


def run(cfg: DictConfig, task_overrides: list[str] | None = None) -> dict[str, Any]:
    """`task_overrides`: the command line's overrides (Hydra's), to know whether `model=` was chosen."""
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    typed = check_run_config(container)  # every key, before any stage writes (pairedgta/schema.py owns the run's keys)
    planning.check_roots(container)
    plan = planning.make_plan(container, typed)
    models = plan.models = planning.run_models(typed, planning.model_group_overridden(task_overrides))
    cache = StageCache(typed.cache_dir, typed.cache.verify)
    tracker = open_tracker(typed)  # MLflow is a record: a failing store costs one warning, not the run
    model_names = [m["name"] for m in models.evaluated] if plan.run_pseudo or plan.check_models else []
    with loaded_once(), closing(tracker):  # closed: a background tracker has logged everything
        summary = _run(container, plan, models, cache, tracker, tracker.experiment, model_names, typed)
    return {**summary, "mlflow": tracker.ui_link()}


def _log_invocation(tracker: Recorder, container: dict[str, Any]) -> None:
    tracker.params(config := {k: v for k, v in container.items() if k != "hydra"})
    tracker.config(config)
    tracker.hydra_config()


def _run(container: dict[str, Any], plan: planning.Plan, models: planning.RunModels, cache: StageCache,
         tracker: Recorder, experiment: str, model_names: list[str], typed: RunConfig
         ) -> dict[str, Any]:
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"dataset": None, "evaluate": {}, "plot": None, "stages": results.setdefault("stages", [])}

    if plan.check_models:  # Cityscapes val: a check of the models themselves, not a paired run
        from pairedgta.stages import cityscapes_val

        ctx = planning.pass_context(container, cache, plan, results, typed)
        with tracker.run(run_name(experiment, model_names, [str(container["dataset"].get("name"))])):
            _log_invocation(tracker, container)
            return cityscapes_val.run(ctx, models.evaluated, tracker)

    passes, configs = [], planning.pass_configs(container)  # the run opens before generation: a stop there is recorded
    with tracker.run(run_name(experiment, model_names, [str(c.get("dataset", {}).get("name")) for _, c in configs])):
        _log_invocation(tracker, container)
        for label, pcfg in configs:
            ctx = planning.pass_context(pcfg, cache, plan, results, typed if pcfg is container else None)
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
        state = planning.RunState(plan, models, tracker, experiment, len(passes) > 1, summary)
        if plan.run_pseudo:
            for ctx, p in ((c, q) for c, q in passes if q.dataset is not None):
                with p.reading():  # a blank or converted image: one warning for the dataset, when its stages are done
                    p.record_dataset(tracker)
                    for stage in PASS_STAGES:
                        stage.step(ctx, p, state)
        if plan.plotting:
            for stage in RUN_STAGES:
                stage.step(passes[0][0], [p for _, p in passes], state)
    return summary
