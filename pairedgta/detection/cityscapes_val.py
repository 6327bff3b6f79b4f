"""Cityscapes-val check for detectors (the work of the `cityscapes_val` stage for task=detection,
`+experiment=cityscapes_val_check task=detection`): box AP per
class against gtFine's instance ids (`*_gtFine_instanceIds.png`: tight boxes of each instance, groups as crowd
regions, regions under 100 px ignored; pairedgta/detection/real_boxes.py) through pycocotools. Cityscapes has no
official box evaluation (its instance benchmark scores masks); these are the COCO conventions MMDetection's
Cityscapes converter uses. A detector whose boxes nearly never match (AP50 under 0.05 with boxes given) is set up
wrong -- channel order, scale, class mapping, box format -- and the check says so in one line."""
from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import pandas as pd
from tqdm import tqdm

from pairedgta.datasets.cityscapes import CityscapesSplit
from pairedgta.detection.boxes import INSTANCE_CLASSES, Box, coco_ground_truth
from pairedgta.detection.real_boxes import read_cityscapes_boxes
from pairedgta.entries import Context, StageResult, model_hash_config
from pairedgta.errors import ConfigError
from pairedgta.jsonio import write_json
from pairedgta.metrics.coco_ap import average_precision, results_format
from pairedgta.models import shared_model
from pairedgta.work import Work

log = logging.getLogger("pairedgta.cityscapes_val")
STAGE = "cityscapes_val"
VERSION = "det1"
SETUP_AP50 = 0.05


def _scaled(boxes: list[Box], scale: float) -> list[Box]:
    if scale == 1.0:
        return boxes
    return [dataclasses.replace(b, xyxy=tuple(v * scale for v in b.xyxy), area=b.area * scale * scale) for b in boxes]


def setup_warning(model: str, ap50: float, boxes: int) -> str | None:
    if boxes and math.isfinite(ap50) and ap50 < SETUP_AP50:
        return (f"{model}: Cityscapes box AP50 {ap50:.3f} with {boxes} boxes given: nearly none matches; check the input "
                "(RGB vs BGR, scale, mean/std), the class mapping and the box format")
    return None


def compute(dataset: CityscapesSplit, model_cfg: dict[str, Any], out: Path, device: str, max_detections: int,
            min_area: int, task: str) -> dict[str, Any]:
    detector = shared_model(model_cfg, device=device)
    model = model_cfg["name"]
    images, gts, results = [], [], []
    missing = [s.frame_id for s in dataset.samples if s.instances is None]
    if missing:
        raise ConfigError(f"dataset.root={dataset.root}: {len(missing)} image(s) have no *_gtFine_instanceIds.png "
                          f"(e.g. {missing[0]}); box AP needs gtFine's instance ids")
    for i, sample in enumerate(tqdm(dataset.samples, desc=f"{STAGE} [{model}]", unit="img"), start=1):
        image, _ = dataset.load(sample)
        d = detector.detect(image[None])[0]
        images.append((i, sample.frame_id, image.shape[1], image.shape[0]))
        gts.append(_scaled(read_cityscapes_boxes(sample.instances, min_area), dataset.scale))
        results += results_format(i, d.boxes, d.scores, d.labels + 1, max_detections)
    gt = coco_ground_truth(images, gts)
    ap = average_precision(gt, results, max_detections)
    rows = [{"model": model, "class_name": "all", "ap": ap["ap"], "ap50": ap["ap50"], "ap75": ap["ap75"]}]
    rows += [{"model": model, "class_name": n, "ap": ap["per_class"][k + 1][0], "ap50": ap["per_class"][k + 1][1],
              "ap75": math.nan} for k, n in enumerate(INSTANCE_CLASSES)]
    pd.DataFrame(rows).to_csv(out / "box_ap.csv", index=False)
    confident = sum(r["score"] >= detector.score_threshold for r in results)
    summary = {"task": task, "model": model, "dataset": dataset.name, "split": dataset.split,
               "scale": dataset.scale, "n_images": len(images), "ap": ap["ap"], "ap50": ap["ap50"], "ap75": ap["ap75"],
               "objects": sum(not b.ignore for bs in gts for b in bs), "confident_boxes": int(confident),
               "warning": setup_warning(model, ap["ap50"], confident)}
    write_json(out / "summary.json", summary)
    return {"ap": ap["ap"]}


@dataclass(frozen=True)
class DetectionCityscapesVal(Work):
    """The `cityscapes_val` stage's work for detection (pairedgta.work.CheckWork)."""

    ENTRY_VERSION: ClassVar[str] = VERSION
    result_cls: type[StageResult] = StageResult

    def hash_config(self, ctx: Context, dataset: CityscapesSplit, model_cfg: dict[str, Any]) -> dict[str, Any]:
        det = ctx.run.detection
        return {"task": self.task.name, "model": model_hash_config(model_cfg),
                "dataset": {"split": dataset.split, "n_images": len(dataset), "scale": dataset.scale},
                "max_detections": det.max_detections, "min_area": det.min_area}

    def compute(self, ctx: Context, dataset: CityscapesSplit, dataset_key: str, model_cfg: dict[str, Any],
                out: Path) -> dict[str, Any]:
        det = ctx.run.detection
        return compute(dataset, model_cfg, out, ctx.run.device, det.max_detections, det.min_area, self.task.name)

    def files(self, result: StageResult) -> list[Path]:
        return [result.path / "box_ap.csv", result.path / "summary.json"]

    def report(self, result: StageResult, model_cfg: dict[str, Any]) -> tuple[dict[str, float], dict[str, Any]]:
        s = json.loads((result.path / "summary.json").read_text())
        log.info("%s [%s]: box AP %.3f, AP50 %.3f over %d %s images (%d objects)", STAGE, model_cfg["name"], s["ap"],
                 s["ap50"], s["n_images"], s["split"], s["objects"])
        if s.get("warning"):
            log.warning("%s", s["warning"])
        metrics = {f"{STAGE}/{k}": s[k] for k in ("ap", "ap50", "ap75")
                   if isinstance(s[k], (int, float)) and math.isfinite(s[k])}
        return metrics, {"ap": s["ap"], "ap50": s["ap50"], "warning": s.get("warning")}


__all__ = ["DetectionCityscapesVal", "SETUP_AP50", "compute", "setup_warning"]
