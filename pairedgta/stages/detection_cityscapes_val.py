"""Cityscapes-val check for detectors (task=detection, `+experiment=cityscapes_val_check task=detection`): box AP per
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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd
from tqdm import tqdm

from pairedgta.datasets import image_notes, open_dataset
from pairedgta.datasets.cityscapes import CityscapesSplit
from pairedgta.detection.boxes import INSTANCE_CLASSES, Box, coco_ground_truth
from pairedgta.detection.real_boxes import read_cityscapes_boxes
from pairedgta.errors import ConfigError
from pairedgta.jsonio import write_json
from pairedgta.metrics.coco_ap import average_precision, results_format
from pairedgta.models import shared_segmenter
from pairedgta.stages.common import Context, StageResult, Unsharded, model_hash_config, run_cached

if TYPE_CHECKING:
    from pairedgta.stages.planning import PassResult, RunState

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
            min_area: int) -> dict[str, Any]:
    detector = shared_segmenter(model_cfg, device=device)
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
    summary = {"task": "detection", "model": model, "dataset": dataset.name, "split": dataset.split,
               "scale": dataset.scale, "n_images": len(images), "ap": ap["ap"], "ap50": ap["ap50"], "ap75": ap["ap75"],
               "objects": sum(not b.ignore for bs in gts for b in bs), "confident_boxes": int(confident),
               "warning": setup_warning(model, ap["ap50"], confident)}
    write_json(out / "summary.json", summary)
    return {"ap": ap["ap"]}


@dataclasses.dataclass
class DetectionCityscapesVal(Unsharded):
    """The detector check (pairedgta.stages.common.Stage) on Cityscapes val; outside the paired graph."""

    ctx: Context
    dataset: CityscapesSplit
    dataset_key: str
    model_cfg: dict[str, Any]
    name: str = STAGE
    version: str = VERSION
    resumable: bool = False
    result_cls: type[StageResult] = StageResult

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        det = self.ctx.run.detection
        return {"task": "detection", "model": model_hash_config(self.model_cfg),
                "dataset": {"split": self.dataset.split, "n_images": len(self.dataset), "scale": self.dataset.scale},
                "max_detections": det.max_detections, "min_area": det.min_area}

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        det = self.ctx.run.detection
        return compute(self.dataset, self.model_cfg, out, self.ctx.run.device, det.max_detections, det.min_area)


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """Every evaluated detector on the Cityscapes split, each in a nested MLflow run; AP in the run's summary."""
    from pairedgta.tracking import bundle, dataset_label, run_name

    dataset = open_dataset(ctx.cfg["dataset"])
    if not isinstance(dataset, CityscapesSplit):
        raise ConfigError(f"stages=[{STAGE}] checks models on Cityscapes; set dataset=cityscapes dataset.root=PATH")
    dataset_key = f"cityscapes:{dataset.fingerprint()}"
    tracker = state.recorder
    tracker.tags({"dataset": dataset.name, "dataset_key": dataset_key, "split": dataset.split, "task": "detection"})
    state.summary["dataset"] = str(dataset.root)
    state.summary[STAGE] = {}
    own = dataclasses.replace(ctx, stages=[*ctx.stages, STAGE])
    with image_notes(f"dataset {dataset.name}"):
        for model_cfg in state.models.evaluated:
            name = model_cfg["name"]
            with tracker.run(run_name(tracker.experiment, [name], [dataset_label(dataset.name, dataset_key)]), nested=True):
                result = run_cached(own, DetectionCityscapesVal(own, dataset, dataset_key, model_cfg))
                s = json.loads((result.path / "summary.json").read_text())
                tracker.params({"model": model_cfg, "dataset": ctx.cfg["dataset"]})
                tracker.tags({f"{STAGE}_hash": result.key, "cache_hit": str(result.hit), "model": name})
                tracker.metrics({f"{STAGE}/{k}": s[k] for k in ("ap", "ap50", "ap75")
                                 if isinstance(s[k], (int, float)) and math.isfinite(s[k])})
                tracker.stage_files(bundle(STAGE, result.key), result.hit,
                                    [result.path / "box_ap.csv", result.path / "summary.json"], STAGE)
            log.info("%s [%s]: box AP %.3f, AP50 %.3f over %d %s images (%d objects)", STAGE, name, s["ap"], s["ap50"],
                     s["n_images"], s["split"], s["objects"])
            if s.get("warning"):
                log.warning("%s", s["warning"])
            state.summary["evaluate"][name] = str(result.path)
            state.summary[STAGE][name] = {"ap": s["ap"], "ap50": s["ap50"], "warning": s.get("warning")}
