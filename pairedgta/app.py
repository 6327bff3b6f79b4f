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
from pairedgta.models.runtime import reuse_freed_memory
from pairedgta.schema import RunConfig
from pairedgta.stages import planning
from pairedgta.tracking import Recorder, dataset_label, open_tracker, run_name

log = logging.getLogger("pairedgta")
# The stages run in the order of pairedgta/stage_registry.py, each through its module's `step(ctx, pass, state)`
# (pairedgta.stages.planning.Step), by scope: "dataset" opens each pass's dataset, "pass" runs over each open pass,
# "run" once over every pass, "check" alone. The plan says which of them run (stages/planning.py Plan.steps).


def run(cfg: DictConfig, task_overrides: list[str] | None = None) -> dict[str, Any]:
    """`task_overrides`: the command line's overrides (Hydra's), to know whether `model=` was chosen."""
    reuse_freed_memory()  # the CPU forward twice as fast: pairedgta/models/runtime.py
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    typed = check_run_config(container)  # every key, before any stage writes (pairedgta/schema.py owns the run's keys)
    planning.check_roots(container)
    plan = planning.make_plan(container, typed)
    models = plan.models = planning.run_models(typed, planning.model_group_overridden(task_overrides))
    cache = StageCache(typed.cache_dir, typed.cache.verify)
    tracker = open_tracker(typed)  # MLflow is a record: a failing store costs one warning, not the run
    model_names = [m["name"] for m in models.evaluated] if plan.steps("pass", "check") else []
    with loaded_once(), closing(tracker):  # closed: a background tracker has logged everything
        if model_names:
            preflight(models, typed.device)
        summary = _run(container, plan, models, cache, tracker, tracker.experiment, model_names, typed)
    return {**summary, "mlflow": tracker.ui_link()}


def preflight(models: planning.RunModels, device: str) -> None:
    """A researcher's model (a model source) is loaded and probed before any stage writes: a missing file, a file of
    another format, a wrong output is its one line now, not after the scenes are rendered. Loaded once: the stages
    reuse it (pairedgta/models: shared_model)."""
    from pairedgta.models import is_source, shared_model

    for cfg in [*models.evaluated, models.reference]:
        if is_source(cfg):
            shared_model(cfg, device=device)


def _log_invocation(tracker: Recorder, container: dict[str, Any]) -> None:
    tracker.params(config := {k: v for k, v in container.items() if k != "hydra"})
    tracker.config(config)
    tracker.hydra_config()


def _run(container: dict[str, Any], plan: planning.Plan, models: planning.RunModels, cache: StageCache,
         tracker: Recorder, experiment: str, model_names: list[str], typed: RunConfig
         ) -> dict[str, Any]:
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"dataset": None, "evaluate": {}, "plot": None, "stages": results.setdefault("stages", [])}

    if checks := plan.steps("check"):  # Cityscapes val: a check of the models themselves, not a paired run
        ctx = planning.pass_context(container, cache, plan, results, typed)
        label = str(container["dataset"].get("name"))
        state = planning.RunState(plan, models, tracker, experiment, False, summary,
                                  passes=[planning.bare_pass(label, ctx)])
        with tracker.run(run_name(experiment, model_names, [label])):
            _log_invocation(tracker, container)
            for spec in checks:
                spec.step(ctx, state.passes[0], state)
        return summary

    configs, contexts = planning.pass_configs(container), []  # the run opens before generation: a stop is recorded
    state = planning.RunState(plan, models, tracker, experiment, len(configs) > 1, summary)
    with tracker.run(run_name(experiment, model_names, [str(c.get("dataset", {}).get("name")) for _, c in configs])):
        _log_invocation(tracker, container)
        for label, pcfg in configs:
            ctx = planning.pass_context(pcfg, cache, plan, results, typed if pcfg is container else None)
            p = planning.open_pass(label, ctx, plan)
            for spec in plan.steps("dataset"):  # generate: renders and opens the dataset when dataset.root is null
                spec.step(ctx, p, state)
            contexts.append(ctx)
            state.passes.append(p)
            if p.dataset is not None:
                log.info("dataset %s%s: %d groups, reference %s", p.dataset.name, f" ({label})" if len(configs) > 1 else "",
                         len(p.dataset), p.dataset.reference)
                summary["dataset"] = summary["dataset"] or str(p.dataset.root)
        passes = state.passes
        tracker.rename(run_name(experiment, model_names, [dataset_label(p.dataset.name, p.dataset_key) for p in passes
                                                           if p.dataset is not None]))
        tracker.tags({"dataset": passes[0].dataset.name if passes[0].dataset else "none",
                      "dataset_key": str(passes[0].dataset_key), "passes": ", ".join(p.label for p in passes),
                      "models": ", ".join(model_names)})
        if steps := plan.steps("pass"):
            for ctx, p in ((c, q) for c, q in zip(contexts, passes) if q.dataset is not None):
                with p.reading():  # a blank or converted image: one warning for the dataset, when its stages are done
                    p.record_dataset(tracker)
                    for spec in steps:
                        spec.step(ctx, p, state)
        for spec in plan.steps("run"):  # once over every pass: the first pass's context, every pass in state.passes
            spec.step(contexts[0], passes[0], state)
    return summary
