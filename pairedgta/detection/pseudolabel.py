"""Detection's pseudo-labels (the work of the `pseudolabel` stage for task=detection): the reference detector's boxes on each group's clean image with
score >= tau (0.6, as the paper's pixels) are the weak ground truth detection xi counts; beside them, the true boxes
of every condition from the renderer's instance masks (pairedgta/detection/boxes.py), written as COCO JSON so the
data goes to any other tool. Both are labels of the dataset, so they share this entry: keyed by the reference
detector, tau and the ground truth's rules."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from tqdm import tqdm

from pairedgta.datasets import PairedDataset, load_image
from pairedgta.datasets.base import image_size
from pairedgta.detection import boxes as gtboxes
from pairedgta.detection.ground_truth import group_ground_truth
from pairedgta.detection.inputs import detections_from_json, detections_json, image_ids
from pairedgta.entries import Context, StageResult, model_hash_config
from pairedgta.jsonio import write_json
from pairedgta.models import shared_model
from pairedgta.models.detectors import Detections
from pairedgta.work import Work

log = logging.getLogger("pairedgta.pseudolabel")
VERSION = "det1"
PSEUDO = "pseudo_boxes.json"
GT_DIR = "ground_truth"
SUMMARY = "labels_summary.json"


def write_json_atomic(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, obj, indent=None)


def boxes_by_group(coco: dict[str, Any]) -> dict[str, list[gtboxes.Box]]:
    """One condition's COCO ground truth (as `write_ground_truth` writes it) back as boxes per group."""
    by_image = {im["id"]: im["pairedgta_group"] for im in coco["images"]}
    out: dict[str, list[gtboxes.Box]] = {gid: [] for gid in by_image.values()}
    for a in coco["annotations"]:
        x, y, w, h = a["bbox"]
        out[by_image[a["image_id"]]].append(gtboxes.Box(
            int(a["instance"]), int(a["category_id"]) - 1, (x, y, x + w, y + h), float(a["area"]),
            str(a.get("ignore_reason", "")), bool(a.get("truncated")), float(a.get("transmittance", "nan"))))
    return out


class DetectionLabels(StageResult):
    """The entry: the reference's confident clean boxes per group, and the ground truth per condition."""

    def boxes(self) -> dict[str, Detections]:
        raw = json.loads((self.path / PSEUDO).read_text())
        return {gid: detections_from_json(d) for gid, d in raw["groups"].items()}

    def ground_truth_file(self, condition: str) -> Path | None:
        p = self.path / GT_DIR / f"{condition}.json"
        return p if p.is_file() else None

    def coco(self, condition: str) -> dict[str, Any] | None:
        """The COCO ground truth of `condition` as written (pycocotools' input); None without ground truth."""
        p = self.ground_truth_file(condition)
        return None if p is None else json.loads(p.read_text())

    def ground_truth(self, condition: str) -> dict[str, list[gtboxes.Box]] | None:
        """Per group the boxes under `condition` (ignore regions included, flagged); None without ground truth."""
        coco = self.coco(condition)
        return None if coco is None else boxes_by_group(coco)

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / SUMMARY).read_text())

    def reference_model(self) -> str:
        return str(self.manifest()["config"]["reference_model"]["name"])

    def tau(self) -> float:
        return float(self.manifest()["config"]["tau"])

    def artifacts(self) -> list[Path]:
        return [p for p in (self.path / SUMMARY, self.path / PSEUDO) if p.is_file()] + \
            sorted((self.path / GT_DIR).glob("*.json"))


def condition_ground_truth(dataset: PairedDataset, cond: str, min_area: int, min_transmittance: float,
                           ids: dict[str, int] | None = None) -> tuple[dict[str, Any], list[list[gtboxes.Box]]] | None:
    """The COCO ground truth of one condition (its images named relative to the dataset root, each tagged with its
    group) and the boxes per image; None where no group has instance masks under it."""
    ids = ids if ids is not None else image_ids(dataset)
    images, per_image, gids = [], [], []
    for g in dataset.groups:
        if cond not in g.images:
            continue
        boxes = group_ground_truth(g, cond, dataset.reference, min_area=min_area, min_transmittance=min_transmittance)
        if boxes is None:
            continue
        w, h = image_size(g.images[cond])
        images.append((ids[g.group_id], str(g.images[cond].relative_to(dataset.root)), w, h))
        per_image.append(boxes)
        gids.append(g.group_id)
    if not images:
        return None
    coco = gtboxes.coco_ground_truth(images, per_image)
    for im, gid in zip(coco["images"], gids):
        im["pairedgta_group"] = gid
    coco["info"].update(condition=cond, min_area=min_area, min_transmittance=min_transmittance)
    return coco, per_image


def write_ground_truth(dataset: PairedDataset, out: Path, min_area: int, min_transmittance: float) -> dict[str, Any]:
    """COCO JSON per condition (ground_truth/<condition>.json); counts of objects and ignore regions."""
    ids = image_ids(dataset)
    counts: dict[str, Any] = {}
    for cond in dataset.conditions:
        found = condition_ground_truth(dataset, cond, min_area, min_transmittance, ids)
        if found is None:
            continue
        coco, per_image = found
        write_json_atomic(out / GT_DIR / f"{cond}.json", coco)
        flat = [b for bs in per_image for b in bs]
        counts[cond] = {"images": len(per_image), "objects": sum(not b.ignore for b in flat),
                        **{f"ignored_{r}": sum(b.ignore == r for b in flat) for r in ("small", "fog")},
                        "truncated": sum(b.truncated for b in flat)}
    return counts


def compute(ctx: Context, dataset: PairedDataset, out: Path, model_cfg: dict[str, Any], tau: float) -> dict[str, Any]:
    detector = shared_model(model_cfg, device=ctx.run.device)
    groups: dict[str, Any] = {}
    per_class = np.zeros(gtboxes.NUM_INSTANCE_CLASSES, np.int64)
    batch = max(1, ctx.run.pseudolabel.batch_size)
    order = dataset.groups
    for i in tqdm(range(0, len(order), batch), desc=f"pseudolabel [{detector.name}]", unit="batch"):
        chunk = order[i:i + batch]
        images = [load_image(g.images[dataset.reference]) for g in chunk]
        shapes = {im.shape for im in images}
        found = detector.detect(np.stack(images)) if len(shapes) == 1 else \
            [detector.detect(im[None])[0] for im in images]
        for g, d in zip(chunk, found):
            kept = d.above(tau)
            groups[g.group_id] = detections_json(kept)
            per_class += np.bincount(kept.labels, minlength=gtboxes.NUM_INSTANCE_CLASSES)
    write_json_atomic(out / PSEUDO, {"reference_model": model_cfg["name"], "tau": tau, "reference": dataset.reference,
                                     "classes": list(gtboxes.INSTANCE_CLASSES), "box_format": "xyxy pixels",
                                     "groups": groups})
    det = ctx.run.detection
    gt = write_ground_truth(dataset, out, det.min_area, ctx.run.metric.min_transmittance)
    if not gt:
        log.warning("pseudolabel: dataset %s has no instance masks or boxes: ground-truth AP is skipped, detection xi "
                    "is still computed", dataset.name)
    summary = {"groups": len(groups), "pseudo_boxes": int(per_class.sum()),
               "pseudo_boxes_per_class": dict(zip(gtboxes.INSTANCE_CLASSES, per_class.tolist())),
               "ground_truth": gt, "tau": tau, "reference_model": model_cfg["name"]}
    write_json_atomic(out / SUMMARY, summary)
    return {"groups": len(groups), "pseudo_boxes": int(per_class.sum())}


@dataclass(frozen=True)
class DetectionPseudolabels(Work):
    """The `pseudolabel` stage's work for detection (pairedgta.work.PseudolabelWork): keyed by the reference
    detector, tau and the ground truth's rules."""

    ENTRY_VERSION: ClassVar[str] = VERSION
    result_cls: type[DetectionLabels] = DetectionLabels

    def hash_config(self, ctx: Context, dataset: PairedDataset, model_cfg: dict[str, Any]) -> dict[str, Any]:
        det = ctx.run.detection
        return {"task": self.task.name, "reference_model": model_hash_config(model_cfg),
                "tau": ctx.run.pseudolabel.tau, "reference": dataset.reference, "threads": ctx.run.threads,
                "ground_truth": {"min_area": det.min_area, "min_transmittance": ctx.run.metric.min_transmittance,
                                 "rules": gtboxes.RULES_VERSION}}

    def compute(self, ctx: Context, dataset: PairedDataset, out: Path, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return compute(ctx, dataset, out, model_cfg, ctx.run.pseudolabel.tau)


__all__ = ["DetectionLabels", "DetectionPseudolabels", "boxes_by_group", "compute", "condition_ground_truth",
           "write_ground_truth",
           "write_json_atomic"]
