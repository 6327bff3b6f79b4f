"""Segmentation's evaluation (the work of the `evaluate` stage for task=segmentation), per model: xi per condition
and class (eq. class_reference_consistency), pixel agreement, phi per image and class (eq. prediction_mass) and
rho_valid (eq. valid_spearman), with percentile-bootstrap intervals over images; ground-truth IoU per condition where
that condition's labels exist (or the reference's, when only the reference is labelled) and xi-vs-ground-truth only
where the reference condition itself is labelled.

The counting, tables and shard parts are this package's (counting, tables, shards, entry): per image only a few
per-class counts are kept, never predictions' probabilities, so memory does not grow with the image size times the
number of images. The stage (pairedgta/stages/evaluate.py) keys, caches, shards and records it."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.conditions import headline_condition
from pairedgta.datasets import PairedDataset
from pairedgta.entries import Context, ModelEntry, model_hash_config
from pairedgta.evaluation import counting, entry, registry, setup_check, shards, tables
from pairedgta.evaluation.counting import GT
from pairedgta.evaluation.inputs import start_workers_server
from pairedgta.evaluation.pseudolabel import PseudoLabels
from pairedgta.evaluation.settings import metric_settings
from pairedgta.models import is_source, shared_model
from pairedgta.models.runtime import torch_threads
from pairedgta.schema import as_dict

log = logging.getLogger("pairedgta.evaluate")
VERSION = "8"  # the framework's; the registered metrics' versions join it past VERSION 8 (registry.stage_version). 8: label-free estimator sums (est_* in group_counts.npz), estimators.csv, predictions.npz; 7: top-M rho_valid only over frames that show the class, no zero-width interval, xi.csv `classes`; 6: metric.min_transmittance (xi.csv column); 2: metric conventions recorded in every output; mIoU over TP+FP+FN > 0; 3: groups_per_condition under random_one
# 4: group_counts.npz (per-group counts: the bootstrap of a comparison across models resamples groups)
# 5: xi.csv `images`/`supported` (metric.min_images/min_pixels); no interval for a class seen in one image;
#    random_one draws a time of day, then a weather of it (the authors' loader)


class EvaluateResult(ModelEntry):
    """One model's evaluate entry and the readers of its files, derived from the registered metrics
    (`pairedgta/evaluation/registry.py`: each metric names and reads its own files; no other code names them).
    `complete` is False for a shard job's partial result (nothing to read yet)."""

    complete: bool = True

    @property
    def FILES(self) -> tuple[str, ...]:
        return registry.result_files()

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


def count_groups(ctx: Context, dataset: PairedDataset, pseudo: PseudoLabels, model_cfg: dict[str, Any],
                 conditions: list[str], groups: list[Any], s: dict[str, Any], maps: Any = None) -> list[dict[str, Any]]:
    """The groups' counts (`counting.group_counts`) under the metric settings `s` (the ones the stage hashed):
    the model on `device`, with `threads` inference threads, images decoded by `evaluate.num_workers` workers."""
    if not groups:
        return []
    device, ev = ctx.run.device, ctx.run.evaluate
    workers = ev.decode_workers(device)
    start_workers_server(workers)  # imports torch beside the model's loading
    segmenter = shared_model(model_cfg, device=device)
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


def label_tags(model_cfg: dict[str, Any]) -> dict[str, str]:
    """The MLflow tags of a model that cannot predict some Cityscapes classes: `unpredictable_classes`
    (comma-separated) and `label_space`; none where it can predict every class (as summary.json's keys)."""
    space, unpredictable = entry.label_space(model_cfg)
    return {"unpredictable_classes": ",".join(unpredictable), "label_space": space} if unpredictable else {}


def xi_table(xi: Any) -> Any:
    """An evaluation's xi.csv as the MLflow table the UI lines up across runs: model, reference, condition
    (the grid's name), class, xi and its bootstrap interval."""
    if xi.empty:
        return xi
    cols = {"model": "model", "reference_model": "reference", "condition": "condition", "class_name": "class",
            "xi": "xi", "ci_low": "ci_low", "ci_high": "ci_high"}
    return xi[list(cols)].rename(columns=cols).reset_index(drop=True)


@dataclass(frozen=True)
class SegmentationEvaluate:
    """The `evaluate` stage's work for segmentation (pairedgta.work.EvaluateWork)."""

    task: Any
    result_cls: type[EvaluateResult] = EvaluateResult

    def version(self, model_cfg: dict[str, Any]) -> str:
        version = registry.stage_version(VERSION)  # the registered metrics' declaration, past VERSION 8
        # a model source's entry holds its set-up check (zoo entries as they were)
        return version + setup_check.VERSION_TAG if is_source(model_cfg) else version

    def settings(self, ctx: Context, dataset: PairedDataset) -> dict[str, Any]:
        return metric_settings(ctx.run, (dataset.grid or ctx.grid).names, dataset.reference)

    def hash_config(self, model_cfg: dict[str, Any], settings: dict[str, Any], conditions: list[str],
                    threads: int) -> dict[str, Any]:
        return {"model": model_hash_config(model_cfg), "metric": settings, "conditions": conditions, "threads": threads}

    def compute(self, ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: PseudoLabels,
                model_cfg: dict[str, Any], conditions: list[str], settings: dict[str, Any], out: Path,
                parts: Path) -> dict[str, Any]:
        summary = compute(ctx, dataset, pseudo, model_cfg, conditions, settings, pseudo.reference_model(), out,
                          parts=parts)
        if is_source(model_cfg):  # the first evaluation of a researcher's model: is it set up right?
            setup_check.store(out, model_cfg["name"], shared_model(model_cfg, device=ctx.run.device), dataset,
                              setup_check.place(ctx.cfg, dataset_key, dataset.name), summary, threads=ctx.run.threads)
        return summary

    def groups(self, ctx: Context, dataset: PairedDataset, pseudo: PseudoLabels, model_cfg: dict[str, Any],
               conditions: list[str], groups: list[Any], settings: dict[str, Any]) -> list[dict[str, Any]]:
        return count_groups(ctx, dataset, pseudo, model_cfg, conditions, groups, settings)

    def read_parts(self, parts: Path) -> dict[str, dict[str, Any]]:
        return shards.read_parts(parts)

    def write_part(self, parts: Path, shard: int, num: int, results: list[dict[str, Any]]) -> None:
        shards.write_part(parts, shard, num, results)

    def said(self, result: EvaluateResult, model_cfg: dict[str, Any]) -> None:
        if is_source(model_cfg):
            setup_check.report(result.path)  # its one WARNING line, computed now or read from the cached entry

    def record(self, ctx: Context, result: EvaluateResult, model_cfg: dict[str, Any]
               ) -> tuple[dict[str, Any], dict[str, str], dict[str, Any]]:
        return {"metric": as_dict(ctx.run.metric)}, label_tags(model_cfg), {"xi_table.json": xi_table(result.xi())}


__all__ = ["EvaluateResult", "SegmentationEvaluate", "compute", "count_groups", "label_tags", "xi_table"]
