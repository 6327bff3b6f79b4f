"""Evaluate stage, per model: the model on every condition of every group, scored against the pass's pseudo-labels
by the run's task's work (pairedgta/tasks.py `Task.work`: segmentation's xi, phi, rho_valid and GT IoU in
pairedgta/evaluation/work.py; detection's xi, pseudo-AP, COCO AP and rPC in pairedgta/detection/evaluate.py).

This module is the stage, the same for every task: what it hashes, its cache entry, its shard jobs (shard i of N does
groups i, i+N, ... and leaves their partial results for the unsharded run to merge), the cached evaluations of other
models a sweep left (plot.collect_cached) and each model's nested MLflow run."""
from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pairedgta.cache import canonical_json
from pairedgta.datasets import PairedDataset
from pairedgta.entries import StageResult
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.evaluation.settings import conditions_for
from pairedgta.stages.common import Context, TaskStage, run_cached

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

log = logging.getLogger("pairedgta.evaluate")


def parts_dir(ctx: Context, key: str) -> Path:
    """Where shard jobs of the entry `key` leave their partial results until the unsharded run merges them."""
    return ctx.cache.root / "evaluate" / f".parts-{key}"


@dataclass
class Evaluate(TaskStage):
    """The evaluate stage (pairedgta.stages.common.Stage) of one model on one dataset's pseudo-labels (`pseudo`), its
    work a pairedgta.work.EvaluateWork."""

    pseudo: StageResult = field(default=None, kw_only=True)  # type: ignore[assignment]
    name: str = field(default="evaluate", kw_only=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.conditions = conditions_for(self.ctx.run.evaluate, self.dataset.grid or self.ctx.grid)
        self.settings = self.work.settings(self.ctx, self.dataset)

    def hash_config(self) -> dict[str, Any]:
        return self.work.hash_config(self.model_cfg, self.settings, self.conditions, self.ctx.run.threads)

    def inputs(self) -> dict[str, str]:
        return {**super().inputs(), "pseudolabel": self.pseudo.key}

    def parts(self, key: str) -> Path:
        return parts_dir(self.ctx, key)

    def build(self, out: Path, key: str) -> dict[str, Any]:
        from pairedgta import corruption_summary
        from pairedgta.corruptions import parse_name

        extra = self.work.compute(self.ctx, self.dataset, self.dataset_key, self.pseudo, self.model_cfg,
                                  self.conditions, self.settings, out, self.parts(key))
        if any(parse_name(c) for c in self.conditions):  # Cityscapes-C's and Michaelis' summary (P, mPC, rPC)
            corruption_summary.write_entry(out, clean=self.dataset.reference)
        return extra

    def shards(self) -> tuple[int, int]:
        return self.ctx.run.evaluate.num_shards, self.ctx.run.evaluate.shard

    def build_shard(self, key: str) -> Path | None:
        """Shard i of N evaluates groups i, i+N, ... and stores their partial results, which the unsharded build
        merges; None when every group is covered."""
        num, shard = self.shards()
        parts, name, groups = self.parts(key), self.model_cfg["name"], self.dataset.groups
        mine = groups[shard::num]
        done = self.work.read_parts(parts)
        todo = [g for g in mine if g.group_id not in done]
        log.info("evaluate [%s] shard %d of %d: %d of %d groups (%d already done)", name, shard, num,
                 len(mine), len(groups), len(mine) - len(todo))
        if todo:
            results = self.work.groups(self.ctx, self.dataset, self.pseudo, self.model_cfg, self.conditions, todo,
                                       self.settings)
            self.work.write_part(parts, shard, num, [done[g.group_id] for g in mine if g.group_id in done] + results)
        covered = self.work.read_parts(parts)
        if all(g.group_id in covered for g in groups):
            return None
        log.info("evaluate [%s]: %d of %d groups evaluated by shards so far; run the remaining shards, then without "
                 "evaluate.shard to merge", name, len(covered), len(groups))
        return parts


def run(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: StageResult,
        model_cfg: dict[str, Any]) -> Any:
    stage = Evaluate(ctx, dataset, dataset_key, model_cfg, pseudo=pseudo)
    result = run_cached(ctx, stage)
    if result.complete:
        result.extra["model_config"] = dict(model_cfg)  # what later readers (the qualitative figure) rebuild
        shutil.rmtree(stage.parts(result.key), ignore_errors=True)  # merged into the entry
        stage.work.said(result, model_cfg)
    return result


def find_cached(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: StageResult,
                exclude: set[str]) -> list[Any]:
    """Every cached evaluation of this dataset and pseudo-labels under the same settings and conditions (e.g. the
    models of an earlier multirun over `model=`): the newest per model, except the models in `exclude`."""
    probe = Evaluate(ctx, dataset, dataset_key, {"name": ""}, pseudo=pseudo)
    keyed = probe.work.hash_config({}, probe.settings, probe.conditions, ctx.run.threads)
    want = json.loads(canonical_json({k: v for k, v in keyed.items() if k not in ("model", "threads")}))
    want_inputs = {"dataset": dataset_key, "pseudolabel": pseudo.key}
    found: dict[str, tuple[float, Any]] = {}
    for cached in ctx.cache.entries("evaluate"):
        m = cached.manifest
        cfg = m.get("config") or {}
        if m.get("inputs") != want_inputs or {k: cfg.get(k) for k in want} != want:
            continue
        name = str((cfg.get("model") or {}).get("name"))
        if name in exclude:
            continue
        if name not in found or cached.mtime > found[name][0]:
            found[name] = (cached.mtime, probe.result_cls("evaluate", cached.key, cached.path, hit=True))
    return [r for _, r in sorted(found.values(), key=lambda t: t[1].key)]


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass: every model's evaluation, each in a nested MLflow run; with
    plot.collect_cached, the cached evaluations of other models too."""
    from pairedgta.tracking import bundle, dataset_label, run_name

    plan, recorder = state.plan, state.recorder
    collect = plan.plotting and ctx.run.plot.collect_cached
    work = plan.task.work_for("evaluate")
    for model_cfg in state.models.evaluated:
        name = f"{p.label}/{model_cfg['name']}" if state.multi else model_cfg["name"]
        try:
            result = run(ctx, p.dataset, p.dataset_key, p.pseudo, model_cfg)
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
        label = dataset_label(p.dataset.name, p.dataset_key)
        with recorder.run(run_name(state.experiment, [model_cfg["name"]], [label]), nested=True):
            params, tags, tables = work.record(ctx, result, model_cfg)
            recorder.params({"model": model_cfg, **params, "reference_model": state.models.reference["name"]})
            recorder.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit), "dataset": p.dataset.name,
                           "pass": p.label, "model": model_cfg["name"], **tags})
            recorder.metrics(result.metrics(per_class=ctx.run.tracking.class_metrics,
                                             headline=ctx.run.plot.ranking.condition))
            p.record_dataset(recorder)
            recorder.config({**{k: v for k, v in ctx.cfg.items() if k not in ("hydra", "variants")}, "model": model_cfg})
            recorder.stage_files(bundle("evaluate", result.key), result.hit, result.artifacts(), "evaluate",
                                 tables=tables)
            state.model_runs.append((recorder.run_id(), model_cfg["name"], p.label))
        state.summary["evaluate"][name] = str(result.path)
    if collect:
        extra = find_cached(ctx, p.dataset, p.dataset_key, p.pseudo, exclude={e.model for e in p.evaluations})
        if extra:
            log.info("plot: collected %d cached evaluation(s) of this dataset: %s", len(extra),
                     ", ".join(e.model for e in extra))
            p.evaluations.extend(extra)
    if plan.plotting and "evaluate" in plan.needs and not p.evaluations:
        raise ConfigError(f"plot: no evaluation of dataset {p.label} to draw; run it first, e.g. stages=[evaluate,plot]")
