"""Evaluate stage, per model: xi per condition and class (eq. class_reference_consistency), pixel
agreement, phi per image and class (eq. prediction_mass) and rho_valid (eq. valid_spearman), with
percentile-bootstrap intervals over images; ground-truth IoU per condition where that condition's
labels exist (or the reference's, when only the reference is labelled) and xi-vs-ground-truth only
where the reference condition itself is labelled.

This module is the stage: what it hashes, its cache entry and its shard jobs. The work is in
pairedgta/evaluation/ (inputs, per-group counting, tables, shard parts): per image only a few per-class
counts are kept, never predictions' probabilities, so memory does not grow with the image size times
the number of images.
"""
from __future__ import annotations

import json
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from pairedgta.cache import canonical_json
from pairedgta.datasets import PairedDataset
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.evaluation import counting, entry, registry, setup_check, shards, tables
from pairedgta.evaluation.inputs import start_workers_server
from pairedgta.evaluation.counting import GT
from pairedgta.evaluation.settings import conditions_for, metric_settings
from pairedgta.schema import as_dict
from pairedgta.models import is_source, shared_segmenter
from pairedgta.models.runtime import torch_threads
from pairedgta.conditions import headline_condition
from pairedgta.stages.common import (
    Context,
    StageResult,
    model_config_from_hash,
    model_hash_config,
    run_cached,
)
from pairedgta.stages.pseudolabel import PseudoLabels

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

log = logging.getLogger("pairedgta.evaluate")
VERSION = "8"  # the framework's; the registered metrics' versions join it past VERSION 8 (registry.stage_version). 8: label-free estimator sums (est_* in group_counts.npz), estimators.csv, predictions.npz; 7: top-M rho_valid only over frames that show the class, no zero-width interval, xi.csv `classes`; 6: metric.min_transmittance (xi.csv column); 2: metric conventions recorded in every output; mIoU over TP+FP+FN > 0; 3: groups_per_condition under random_one
# 4: group_counts.npz (per-group counts: the bootstrap of a comparison across models resamples groups)
# 5: xi.csv `images`/`supported` (metric.min_images/min_pixels); no interval for a class seen in one image;
#    random_one draws a time of day, then a weather of it (the authors' loader)


class EvaluateResult(StageResult):
    """One model's evaluate entry and the readers of its files, derived from the registered metrics
    (`pairedgta/evaluation/registry.py`: each metric names and reads its own files; no other code names them).
    `complete` is False for a shard job's partial result (nothing to read yet)."""

    complete: bool = True

    @property
    def FILES(self) -> tuple[str, ...]:
        return registry.result_files()

    def model_config(self) -> dict[str, Any]:
        """The model's composed config: as this run built it, or (an evaluation collected from the cache)
        buildable from its manifest (figures re-predict a few groups with it)."""
        if "model_config" in self.extra:
            return dict(self.extra["model_config"])
        return model_config_from_hash(self.manifest()["config"]["model"])

    @property
    def model(self) -> str:
        return str(self.model_config()["name"])

    def read(self, file: str) -> Any:
        """One of the entry's tables, by the reader of the registered metric that writes it."""
        return registry.reader(file).read(self.path / file)

    def xi(self) -> pd.DataFrame:
        return self.read(tables.XI)

    def rho(self) -> pd.DataFrame:
        return self.read(tables.RHO_VALID)

    def frame_counts(self) -> pd.DataFrame:
        return self.read(tables.FRAME_COUNTS)

    def agreement(self) -> pd.DataFrame:
        return self.read(tables.AGREEMENT)

    def gt_iou(self) -> pd.DataFrame:
        return self.read(tables.GT_IOU)

    def summary(self) -> dict[str, Any]:
        return entry.read_summary(self.path)

    def group_counts(self) -> dict[str, np.ndarray]:
        """Per-group counts (see `entry.write_group_counts`); empty for entries written before VERSION 4."""
        return entry.read_group_counts(self.path)

    def artifacts(self) -> list[Path]:
        return [self.path / f for f in self.FILES if (self.path / f).is_file()]

    def metrics(self, per_class: bool = False, headline: str | None = None) -> dict[str, float]:
        """The MLflow view: xi_mean/<cond>, xi_gt_mean/<cond>, gt_miou/<cond>, agreement/<cond> and the
        headline condition's rho_valid/<sel>/<class> (`conditions.headline_condition`: `headline`, the run's
        plot.ranking.condition, when set, as the ranking figure shows); with `per_class` (tracking.class_metrics)
        also xi/<cond>/<class>, xi_gt/<cond>/<class> and rho_valid/<cond>/<sel>/<class>, ten times as many
        metrics (the xi table and xi.csv/rho_valid.csv hold them either way)."""
        metrics: dict[str, float] = {}
        for row in self.xi().itertuples():
            prefix = "xi" if row.reference_model != GT else "xi_gt"
            if row.class_name == "mean":
                metrics[f"{prefix}_mean/{row.condition}"] = row.xi
            elif per_class:
                metrics[f"{prefix}/{row.condition}/{row.class_name}"] = row.xi
        rho = self.rho()
        conds = list(dict.fromkeys(rho["condition"])) if not rho.empty else []
        main = headline_condition(conds, headline)
        for row in rho.itertuples():
            if per_class:
                metrics[f"rho_valid/{row.condition}/{row.selection}/{row.class_name}"] = row.rho
            if row.condition == main:
                metrics[f"rho_valid/{row.selection}/{row.class_name}"] = row.rho
        summary = self.summary()
        for cond, v in summary.get("gt_miou", {}).items():
            metrics[f"gt_miou/{cond}"] = v
        for cond, v in summary.get("agreement", {}).items():
            metrics[f"agreement/{cond}"] = v
        for cond, values in summary.get("estimators", {}).items():
            metrics.update({f"estimator/{name}/{cond}": v for name, v in values.items()
                            if isinstance(v, (int, float)) and math.isfinite(v)})
        return metrics


def find_cached(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: StageResult,
                exclude: set[str]) -> list[EvaluateResult]:
    """Every cached evaluation of this dataset and pseudo-labels under the same metric settings and
    conditions (e.g. the models of an earlier multirun over `model=`): the newest per model, except the
    models in `exclude`."""
    want_inputs = {"dataset": dataset_key, "pseudolabel": pseudo.key}
    grid = dataset.grid or ctx.grid
    settings = json.loads(canonical_json(metric_settings(ctx.run, grid.names, dataset.reference)))
    conditions = conditions_for(ctx.run.evaluate, grid)
    found: dict[str, tuple[float, EvaluateResult]] = {}
    for cached in ctx.cache.entries("evaluate"):
        m = cached.manifest
        cfg = m.get("config") or {}
        if m.get("inputs") != want_inputs or cfg.get("metric") != settings or cfg.get("conditions") != conditions:
            continue
        name = str((cfg.get("model") or {}).get("name"))
        if name in exclude:
            continue
        if name not in found or cached.mtime > found[name][0]:
            found[name] = (cached.mtime, EvaluateResult("evaluate", cached.key, cached.path, hit=True))
    return [r for _, r in sorted(found.values(), key=lambda t: t[1].key)]


def count_groups(ctx: Context, dataset: PairedDataset, pseudo: PseudoLabels, model_cfg: dict[str, Any],
                 conditions: list[str], groups: list[Any], s: dict[str, Any], maps: Any = None) -> list[dict[str, Any]]:
    """The groups' counts (`counting.group_counts`) under the metric settings `s` (the ones the stage hashed):
    the model on `device`, with `threads` inference threads, images decoded by `evaluate.num_workers` workers."""
    if not groups:
        return []
    device, ev = ctx.run.device, ctx.run.evaluate
    workers = ev.decode_workers(device)
    start_workers_server(workers)  # imports torch beside the model's loading
    segmenter = shared_segmenter(model_cfg, device=device)
    with torch_threads(ctx.run.threads):
        return counting.count_groups(dataset, pseudo.labels, segmenter, s, conditions, groups, ev.batch_size,
                                      workers, maps=maps)


def compute(ctx: Context, dataset: PairedDataset, pseudo: PseudoLabels, model_cfg: dict[str, Any], conditions: list[str],
            s: dict[str, Any], reference_model: str, out: Path, parts: Path | None = None) -> dict[str, Any]:
    """Evaluate every group, or merge the partial sums that shard jobs left in `parts` and compute only
    the groups no shard covered; the outputs are the same either way (groups in dataset order).

    The Cityscapes classes the model's label space cannot predict (`entry.label_space`, from model.labels:
    the model config is in the stage's hash, `s` stays the run's metric settings) are NaN in xi.csv and
    gt_iou.csv with that reason, never a silent 0: the mean xi and GT mIoU are over the classes the model can
    predict, and summary.json records which were left out (`unpredictable_classes`, `label_space`)."""
    conv = s["convention"]
    log.info("evaluate: metric convention %s (absent classes %s, mean without %s, %s agreement, rho_valid headline %s), "
             "sampling %s", conv["name"], conv["absent"], list(conv["mean_exclude"]) or "none", conv["agreement"],
             conv["rho_headline"], s["sampling"])
    done = shards.read_parts(parts) if parts is not None else {}
    missing = [g for g in dataset.groups if g.group_id not in done]
    if done:
        log.info("evaluate: merging %d group(s) from shard jobs, computing %d", len(done), len(missing))
    # the label maps go to predictions.npz as they come, unless groups merged from shards must be put between them
    writer = None if done else entry.PredictionWriter(out / entry.PREDICTIONS, conditions)
    try:
        for r in count_groups(ctx, dataset, pseudo, model_cfg, conditions, missing, s,
                              maps=writer.add if writer is not None else None):
            done[r["group_id"]] = r
        return _write(dataset, model_cfg, conditions, s, reference_model, out, done, writer)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise


def _write(dataset: PairedDataset, model_cfg: dict[str, Any], conditions: list[str], s: dict[str, Any],
           reference_model: str, out: Path, done: dict[str, dict[str, Any]],
           writer: entry.PredictionWriter | None) -> dict[str, Any]:
    model = str(model_cfg["name"])
    covered = entry.coverage(dataset, conditions, s["clean"], model, s["sampling"], s["sampling_seed"])
    space, unpredictable = entry.label_space(model_cfg)
    if unpredictable:
        log.warning("evaluate [%s]: cannot predict %s (label space %s): their xi and IoU are NaN, the means are "
                    "over the other classes", model, ", ".join(unpredictable), space)
    evaluation = entry.ModelEvaluation(
        dataset=dataset.name, model=model, reference_model=reference_model, conditions=conditions, settings=s,
        groups=[done[g.group_id] for g in dataset.groups if g.group_id in done], coverage=covered,
        unpredictable=unpredictable, label_space=space)
    return entry.write_outputs(out, evaluation, predictions=writer)


def parts_dir(ctx: Context, key: str) -> Path:
    """Where shard jobs of the entry `key` leave their partial sums until the unsharded run merges them."""
    return ctx.cache.root / "evaluate" / f".parts-{key}"


@dataclass
class Evaluate:
    """The evaluate stage (pairedgta.stages.common.Stage) of one model on one dataset's pseudo-labels."""

    ctx: Context
    dataset: PairedDataset
    dataset_key: str
    pseudo: PseudoLabels
    model_cfg: dict[str, Any]
    name: str = "evaluate"
    version: str = VERSION
    resumable: bool = False
    result_cls: type[EvaluateResult] = EvaluateResult

    def __post_init__(self) -> None:
        self.version = registry.stage_version(self.version)  # the registered metrics' declaration, past VERSION 8
        if is_source(self.model_cfg):  # a model source's entry holds its set-up check (zoo entries as they were)
            self.version += setup_check.VERSION_TAG
        grid = self.dataset.grid or self.ctx.grid
        self.conditions = conditions_for(self.ctx.run.evaluate, grid)
        self.settings = metric_settings(self.ctx.run, grid.names, self.dataset.reference)

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        return {"model": model_hash_config(self.model_cfg), "metric": self.settings, "conditions": self.conditions,
                "threads": self.ctx.run.threads}

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key, "pseudolabel": self.pseudo.key}

    def parts(self, key: str) -> Path:
        return parts_dir(self.ctx, key)

    def build(self, out: Path, key: str) -> dict[str, Any]:
        summary = compute(self.ctx, self.dataset, self.pseudo, self.model_cfg, self.conditions, self.settings,
                          self.pseudo.reference_model(), out, parts=self.parts(key))
        if is_source(self.model_cfg):  # the first evaluation of a researcher's model: is it set up right?
            setup_check.store(out, self.model_cfg["name"], shared_segmenter(self.model_cfg, device=self.ctx.run.device),
                              self.dataset, setup_check.place(self.ctx.cfg, self.dataset_key, self.dataset.name),
                              summary, threads=self.ctx.run.threads)
        return summary

    def shards(self) -> tuple[int, int]:
        return self.ctx.run.evaluate.num_shards, self.ctx.run.evaluate.shard

    def build_shard(self, key: str) -> Path | None:
        """Shard i of N evaluates groups i, i+N, ... and stores their partial sums, which the unsharded build
        merges; None when every group is covered."""
        num, shard = self.shards()
        parts, name, groups = self.parts(key), self.model_cfg["name"], self.dataset.groups
        mine = groups[shard::num]
        done = shards.read_parts(parts)
        todo = [g for g in mine if g.group_id not in done]
        log.info("evaluate [%s] shard %d of %d: %d of %d groups (%d already done)", name, shard, num,
                 len(mine), len(groups), len(mine) - len(todo))
        if todo:
            results = count_groups(self.ctx, self.dataset, self.pseudo, self.model_cfg, self.conditions, todo,
                                   self.settings)
            shards.write_part(parts, shard, num, [done[g.group_id] for g in mine if g.group_id in done] + results)
        covered = shards.read_parts(parts)
        if all(g.group_id in covered for g in groups):
            return None
        log.info("evaluate [%s]: %d of %d groups evaluated by shards so far; run the remaining shards, then without "
                 "evaluate.shard to merge", name, len(covered), len(groups))
        return parts


def run(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: PseudoLabels,
        model_cfg: dict[str, Any]) -> EvaluateResult:
    stage = Evaluate(ctx, dataset, dataset_key, pseudo, model_cfg)
    result = run_cached(ctx, stage)
    assert isinstance(result, EvaluateResult)
    if result.complete:
        result.extra["model_config"] = dict(model_cfg)  # what later readers (the qualitative figure) rebuild
        shutil.rmtree(stage.parts(result.key), ignore_errors=True)  # merged into the entry
        if is_source(model_cfg):
            setup_check.report(result.path)  # its one WARNING line, computed now or read from the cached entry
    return result


def label_tags(model_cfg: dict[str, Any]) -> dict[str, str]:
    """The MLflow tags of a model that cannot predict some Cityscapes classes: `unpredictable_classes`
    (comma-separated) and `label_space`; none where it can predict every class (as summary.json's keys)."""
    space, unpredictable = entry.label_space(model_cfg)
    return {"unpredictable_classes": ",".join(unpredictable), "label_space": space} if unpredictable else {}


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass: every model's evaluation, each in a nested MLflow run; with
    plot.collect_cached, the cached evaluations of other models too."""
    from pairedgta.tracking import bundle, dataset_label, run_name, xi_table

    plan, recorder = state.plan, state.recorder
    collect = plan.plotting and ctx.run.plot.collect_cached
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
            recorder.params({"model": model_cfg, "metric": as_dict(ctx.run.metric), "reference_model": state.models.reference["name"]})
            recorder.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit), "dataset": p.dataset.name,
                           "pass": p.label, "model": model_cfg["name"], **label_tags(model_cfg)})
            recorder.metrics(result.metrics(per_class=ctx.run.tracking.class_metrics,
                                             headline=ctx.run.plot.ranking.condition))
            p.record_dataset(recorder)
            recorder.config({**{k: v for k, v in ctx.cfg.items() if k not in ("hydra", "variants")}, "model": model_cfg})
            recorder.stage_files(bundle("evaluate", result.key), result.hit, result.artifacts(), "evaluate",
                                 tables={"xi_table.json": xi_table(result.xi())})
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
