"""Detection's evaluation (the work of the `evaluate` stage for task=detection), per model: the detector on every
condition of every group, then the detection metrics of pairedgta/detection/registry.py over the stored detections
(detection xi with its precision side and pseudo-AP against the reference's clean boxes; COCO AP, P / mPC / rPC
against the renderer's ground truth; the per-object view). Every model's detections are kept per condition in COCO
results format (detections/<condition>.json), so a user can re-score them elsewhere.

Per group only its detections (at most `detection.max_detections` boxes an image) and a few counts are kept; shard
jobs store those per group and the unsharded run merges them, as segmentation's evaluate does."""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from pairedgta.datasets import PairedDataset, load_group_images
from pairedgta.detection import registry
from pairedgta.detection.boxes import INSTANCE_CLASSES, NUM_INSTANCE_CLASSES
from pairedgta.models.detectors import Detections
from pairedgta.detection.inputs import GroupResult, Inputs, image_ids
from pairedgta.detection.pseudolabel import DetectionLabels, boxes_by_group, write_json_atomic
from pairedgta.entries import Context, ModelEntry, model_hash_config
from pairedgta.errors import ConfigError
from pairedgta.jsonio import write_bytes
from pairedgta.metrics import detection_xi, per_object
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.detection import setup_check
from pairedgta.models import is_source, shared_model
from pairedgta.models.runtime import torch_threads
from pairedgta.schema import as_dict

log = logging.getLogger("pairedgta.evaluate")
VERSION = "det2"  # 2: a source detector's set-up check (pairedgta/detection/setup_check.py)
SUMMARY = "summary.json"
DETECTIONS_DIR = "detections"


class DetectionEvaluateResult(ModelEntry):
    """One detector's evaluate entry; its tables are read by the readers the registered metrics declare."""

    def read(self, file: str) -> pd.DataFrame:
        return pd.read_csv(self.path / file)

    def xi(self) -> pd.DataFrame:
        return self.read(registry.XI)

    def optional(self, file: str, ids: str | None = None) -> pd.DataFrame:
        """One of the entry's tables, empty where the entry has none (no ground truth, no estimators); `ids` keeps
        that column's group or pair ids as written ('00000', not 0)."""
        path = self.path / file
        if not path.is_file():
            return pd.DataFrame()
        return pd.read_csv(path, dtype={ids: str}) if ids else self.read(file)

    def gt_ap(self) -> pd.DataFrame:
        """AP per condition and class against the renderer's boxes; empty without ground truth."""
        return self.optional(registry.GT_AP)

    def robustness(self) -> pd.DataFrame:
        return self.optional(registry.ROBUSTNESS)

    def frame_counts(self) -> pd.DataFrame:
        """phi of boxes per image, class and adverse condition, clean and adverse (the ranking figure's input)."""
        return self.optional(registry.FRAME_COUNTS, ids="pair_id")

    def box_counts(self) -> pd.DataFrame:
        """Per group, condition and class: reference boxes, found, confident, matched (scene resamples)."""
        return self.optional(registry.GROUP_COUNTS, ids="group_id")

    def estimators(self) -> pd.DataFrame:
        """Per group and condition: BoS, pre-NMS consistency (with detection.estimators); empty without them."""
        return self.optional(registry.ESTIMATORS, ids="group_id")

    def objects(self) -> pd.DataFrame:
        return self.optional(registry.OBJECTS, ids="group_id")

    def rho(self) -> pd.DataFrame:
        return self.optional(registry.RHO_VALID)

    def objects_found(self) -> pd.DataFrame:
        return self.optional(registry.OBJECTS_FOUND)

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / SUMMARY).read_text())

    def detections(self, condition: str) -> list[dict[str, Any]]:
        return json.loads((self.path / DETECTIONS_DIR / f"{condition}.json").read_text())

    def artifacts(self) -> list[Path]:
        return [self.path / f for f in (*registry.result_files(), SUMMARY) if (self.path / f).is_file()]

    def metrics(self, per_class: bool = False, headline: str | None = None) -> dict[str, float]:
        """The MLflow view: det_xi_mean/<cond>, pseudo_ap50/<cond>, precision/<cond>, ap/<cond>, ap50/<cond>,
        P/mPC/rPC; with `per_class` also det_xi/<cond>/<class>."""
        s = self.summary()
        out: dict[str, float] = {}
        for key in ("xi_mean", "pseudo_ap50", "precision", "gt_ap", "gt_ap50"):
            for cond, v in (s.get(key) or {}).items():
                if isinstance(v, (int, float)) and math.isfinite(v):
                    out[f"det_{key}/{cond}"] = float(v)
        for k, v in (s.get("robustness") or {}).items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                out[f"det_{k}"] = float(v)
        if per_class:
            for row in self.xi().itertuples():
                if row.class_name != "mean" and math.isfinite(row.xi):
                    out[f"det_xi/{row.condition}/{row.class_name}"] = float(row.xi)
        return out


def _detect_group(detector: Any, group: Any, conditions: list[str], pseudo: Detections, gt: dict[str, Any],
                  threshold: float, iou: float, estimators: bool = False) -> GroupResult:
    images = load_group_images(group, conditions)
    present = [c for c in conditions if c in images]
    found = detector.detect(np.stack([images[c] for c in present])) if present else []
    dets, counts, objects, sizes, extra = {}, {}, [], {}, {}
    for c, d in zip(present, found):
        if estimators:  # BoS and the pre-NMS consistency: two more forwards of this image (the validity study)
            from pairedgta.metrics.box_stability import image_estimators

            seed = zlib_seed(group.group_id, c)
            extra[c] = image_estimators(detector, images[c], d, seed=seed)
        dets[c] = d
        sizes[c] = images[c].shape[:2]
        counts[c] = detection_xi.image_counts(pseudo.boxes, pseudo.labels, d.boxes, d.scores, d.labels, threshold,
                                              iou, NUM_INSTANCE_CLASSES)
        boxes = (gt.get(c) or {}).get(group.group_id)
        if boxes:
            objects += per_object.object_rows(group.group_id, c, boxes, per_object.luma_in_boxes(images[c], boxes),
                                              d.boxes, d.scores, d.labels, threshold, iou, INSTANCE_CLASSES)
    return GroupResult(group.group_id, dets, counts, objects, sizes, extra)


def zlib_seed(group_id: str, condition: str) -> int:
    """A dropout seed per image that does not depend on the run's order (or on PYTHONHASHSEED)."""
    import zlib

    return zlib.crc32(f"{group_id}/{condition}".encode())


def detect_groups(ctx: Context, model_cfg: dict[str, Any], conditions: list[str], groups: list[Any],
                  pseudo: dict[str, Detections], gt: dict[str, Any]) -> list[GroupResult]:
    """The detector on `groups`, against the reference's boxes `pseudo` and the ground truth `gt` (condition ->
    boxes per group, or None), both read once by the caller."""
    if not groups:
        return []
    detector = shared_model(model_cfg, device=ctx.run.device)
    det = ctx.run.detection
    out = []
    with torch_threads(ctx.run.threads):
        for g in tqdm(groups, desc=f"evaluate [{detector.name}]", unit="group"):
            out.append(_detect_group(detector, g, conditions, pseudo.get(g.group_id, Detections.empty()), gt,
                                     detector.score_threshold, det.iou, det.estimators))
    return out


def read_parts(parts: Path) -> dict[str, GroupResult]:
    found: dict[str, GroupResult] = {}
    for path in sorted(parts.glob("part-*.json")) if parts.is_dir() else []:
        try:
            for r in json.loads(path.read_text()):
                found[r["group_id"]] = GroupResult.from_json(r)
        except (OSError, ValueError, KeyError, TypeError):
            log.warning("evaluate: ignoring unreadable shard result %s (its groups are computed again)", path)
    return found


def write_part(parts: Path, shard: int, num: int, results: list[GroupResult]) -> None:
    from pairedgta.jsonio import dumps

    parts.mkdir(parents=True, exist_ok=True)
    write_bytes(parts / f"part-{shard:05d}-of-{num:05d}.json", dumps([r.to_json() for r in results]).encode())


def settings(ctx: Context, reference: str) -> dict[str, Any]:
    m = ctx.run.metric
    conv = convention_from_config(as_dict(m), list(m.rho.selections))  # validates selections, headline, min_frames
    classes = list(m.rho.classes or [])
    unknown = [c for c in classes if c not in INSTANCE_CLASSES]
    if unknown:
        raise ConfigError(f"metric.rho.classes: {unknown} are no detection classes; use some of "
                          f"{', '.join(INSTANCE_CLASSES)}")
    rho = {"m": m.rho.m, "selections": list(m.rho.selections), "headline": conv.rho_headline,
           "min_frames": conv.rho_min_frames, "classes": classes}
    return {**as_dict(ctx.run.detection), "min_images": m.min_images, "min_transmittance": m.min_transmittance,
            "bootstrap": as_dict(m.bootstrap), "clean": reference, "rho": rho}


def compute(ctx: Context, dataset: PairedDataset, labels: DetectionLabels, model_cfg: dict[str, Any],
            conditions: list[str], s: dict[str, Any], out: Path, parts: Path, task: Any, where: str = "the dataset"
            ) -> dict[str, Any]:
    done = read_parts(parts)
    missing = [g for g in dataset.groups if g.group_id not in done]
    if done:
        log.info("evaluate: merging %d group(s) from shard jobs, computing %d", len(done), len(missing))
    pseudo = labels.boxes()
    gts = {c: coco for c in conditions if (coco := labels.coco(c)) is not None}
    boxes = {c: boxes_by_group(gts[c]) if c in gts else None for c in conditions}
    for r in detect_groups(ctx, model_cfg, conditions, missing, pseudo, boxes):
        done[r.group_id] = r
    detector = shared_model(model_cfg, device=ctx.run.device)  # built once per run: the shards' too
    inputs = Inputs(str(model_cfg["name"]), labels.reference_model(), conditions, s["clean"],
                    [done[g.group_id] for g in dataset.groups if g.group_id in done], image_ids(dataset),
                    pseudo, gts, float(detector.score_threshold), s, tuple(getattr(detector, "blind", ())))
    extra = {}
    if is_source(model_cfg):  # a researcher's detector: is it set up as it was trained? (its line on every run)
        extra = setup_check.run(detector, dataset, gts.get(s["clean"]), s["clean"], where)
    return write_outputs(out, inputs, task, extra)


def write_outputs(out: Path, inputs: Inputs, task: Any, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The registered metrics' tables, the detections per condition (COCO results) and summary.json."""
    for cond in inputs.conditions:
        write_json_atomic(out / DETECTIONS_DIR / f"{cond}.json", inputs.coco_results(cond))
    summary: dict[str, Any] = {"task": task.name, "model": inputs.model, "reference_model": inputs.reference_model,
                               "conditions": inputs.conditions, "clean": inputs.clean, "groups": len(inputs.groups),
                               "score_threshold": inputs.threshold, "settings": inputs.settings}
    if not inputs.ground_truth:
        summary["ground_truth"] = "none: the dataset has no instance masks or boxes; GT AP skipped, xi computed"
    for metric in task.metric_list():  # the task's metrics, listed once (pairedgta/detection/registry.py)
        tables, values = metric.compute(inputs)
        for file, table in tables.items():
            tmp = out / f".{file}.tmp"
            table.to_csv(tmp, index=False)
            tmp.replace(out / file)
        summary.update(values)
    summary.update(extra or {})
    write_json_atomic(out / SUMMARY, summary)
    return {k: summary[k] for k in ("groups",)}


@dataclass(frozen=True)
class DetectionEvaluate:
    """The `evaluate` stage's work for detection (pairedgta.work.EvaluateWork)."""

    task: Any
    result_cls: type[DetectionEvaluateResult] = DetectionEvaluateResult

    def version(self, model_cfg: dict[str, Any]) -> str:
        return f"{VERSION}+{'+'.join(registry.versions())}"

    def settings(self, ctx: Context, dataset: PairedDataset) -> dict[str, Any]:
        return settings(ctx, dataset.reference)

    def hash_config(self, model_cfg: dict[str, Any], settings: dict[str, Any], conditions: list[str],
                    threads: int) -> dict[str, Any]:
        return {"task": self.task.name, "model": model_hash_config(model_cfg), "metric": settings,
                "conditions": conditions, "threads": threads}

    def compute(self, ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: DetectionLabels,
                model_cfg: dict[str, Any], conditions: list[str], settings: dict[str, Any], out: Path,
                parts: Path) -> dict[str, Any]:
        from pairedgta.evaluation.setup_check import place

        return compute(ctx, dataset, pseudo, model_cfg, conditions, settings, out, parts, self.task,
                       place(ctx.cfg, dataset_key, dataset.name))

    def groups(self, ctx: Context, dataset: PairedDataset, pseudo: DetectionLabels, model_cfg: dict[str, Any],
               conditions: list[str], groups: list[Any], settings: dict[str, Any]) -> list[GroupResult]:
        gt = {c: pseudo.ground_truth(c) for c in conditions}
        return detect_groups(ctx, model_cfg, conditions, groups, pseudo.boxes(), gt)

    def read_parts(self, parts: Path) -> dict[str, GroupResult]:
        return read_parts(parts)

    def write_part(self, parts: Path, shard: int, num: int, results: list[GroupResult]) -> None:
        write_part(parts, shard, num, results)

    def said(self, result: DetectionEvaluateResult, model_cfg: dict[str, Any]) -> None:
        if result.summary().get("setup_line"):  # computed now or read from the cached entry: said on every run
            log.warning("%s", result.summary()["setup_line"])

    def record(self, ctx: Context, result: DetectionEvaluateResult, model_cfg: dict[str, Any]
               ) -> tuple[dict[str, Any], dict[str, str], dict[str, Any]]:
        options = as_dict(ctx.run.detection)  # the run's detection node: box matching, max detections, min area
        return ({self.task.name: options, "task": self.task.name}, {"task": self.task.name},
                {"det_xi_table.json": xi_table(result.xi())})


def xi_table(xi: pd.DataFrame) -> pd.DataFrame:
    cols = ["model", "reference_model", "condition", "class_name", "xi", "ci_low", "ci_high", "precision", "pseudo_ap50"]
    return xi[[c for c in cols if c in xi.columns]].reset_index(drop=True) if not xi.empty else xi


__all__ = ["DETECTIONS_DIR", "DetectionEvaluate", "DetectionEvaluateResult", "SUMMARY", "compute", "detect_groups",
           "settings", "write_outputs", "xi_table"]
