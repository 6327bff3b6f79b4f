"""Detection's pseudo-label stage (task=detection): the reference detector's boxes on each group's clean image with
score >= tau (0.6, as the paper's pixels) are the weak ground truth detection xi counts; beside them, the true boxes
of every condition from the renderer's instance masks (pairedgta/detection/boxes.py), written as COCO JSON so the
data goes to any other tool. Both are labels of the dataset, so they share this entry: keyed by the reference
detector, tau and the ground truth's rules."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from pairedgta.datasets import PairedDataset, load_image
from pairedgta.datasets.base import image_size
from pairedgta.detection import boxes as gtboxes
from pairedgta.detection.ground_truth import group_ground_truth
from pairedgta.detection.inputs import detections_from_json, detections_json, image_ids
from pairedgta.detection.models import Detections
from pairedgta.jsonio import write_json
from pairedgta.models import shared_segmenter
from pairedgta.models.runtime import torch_threads
from pairedgta.stages.common import Context, StageResult, Unsharded, model_hash_config, run_cached

if TYPE_CHECKING:
    from pairedgta.stages.planning import PassResult, RunState

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


def write_ground_truth(dataset: PairedDataset, out: Path, min_area: int, min_transmittance: float) -> dict[str, Any]:
    """COCO JSON per condition (ground_truth/<condition>.json); counts of objects and ignore regions."""
    ids = image_ids(dataset)
    counts: dict[str, Any] = {}
    for cond in dataset.conditions:
        images, per_image, gids = [], [], []
        for g in dataset.groups:
            if cond not in g.images:
                continue
            boxes = group_ground_truth(g, cond, dataset.reference, min_area=min_area,
                                       min_transmittance=min_transmittance)
            if boxes is None:
                continue
            w, h = image_size(g.images[cond])
            images.append((ids[g.group_id], str(g.images[cond].relative_to(dataset.root)), w, h))
            per_image.append(boxes)
            gids.append(g.group_id)
        if not images:
            continue
        coco = gtboxes.coco_ground_truth(images, per_image)
        for im, gid in zip(coco["images"], gids):
            im["pairedgta_group"] = gid
        coco["info"].update(condition=cond, min_area=min_area, min_transmittance=min_transmittance)
        write_json_atomic(out / GT_DIR / f"{cond}.json", coco)
        flat = [b for bs in per_image for b in bs]
        counts[cond] = {"images": len(images), "objects": sum(not b.ignore for b in flat),
                        **{f"ignored_{r}": sum(b.ignore == r for b in flat) for r in ("small", "fog")},
                        "truncated": sum(b.truncated for b in flat)}
    return counts


def compute(ctx: Context, dataset: PairedDataset, out: Path, model_cfg: dict[str, Any], tau: float) -> dict[str, Any]:
    detector = shared_segmenter(model_cfg, device=ctx.run.device)
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


@dataclass
class DetectionPseudolabel(Unsharded):
    """The detection pseudo-label stage (pairedgta.stages.common.Stage) of one dataset and reference detector."""

    ctx: Context
    dataset: PairedDataset
    dataset_key: str
    model_cfg: dict[str, Any]
    name: str = "pseudolabel"
    version: str = VERSION
    resumable: bool = False
    result_cls: type[DetectionLabels] = DetectionLabels

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        det = self.ctx.run.detection
        return {"task": "detection", "reference_model": model_hash_config(self.model_cfg),
                "tau": self.ctx.run.pseudolabel.tau, "reference": self.dataset.reference, "threads": self.ctx.run.threads,
                "ground_truth": {"min_area": det.min_area, "min_transmittance": self.ctx.run.metric.min_transmittance,
                                 "rules": gtboxes.RULES_VERSION}}

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        with torch_threads(self.ctx.run.threads):
            return compute(self.ctx, self.dataset, out, self.model_cfg, self.ctx.run.pseudolabel.tau)


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass (task=detection): the reference detector's boxes and the ground truth."""
    from pairedgta.tracking import bundle

    p.pseudo = run_cached(ctx, DetectionPseudolabel(ctx, p.dataset, p.dataset_key, state.models.reference))
    assert isinstance(p.pseudo, DetectionLabels)
    state.summary.setdefault("pseudolabel", str(p.pseudo.path))
    state.recorder.stage_files(bundle("pseudolabel", p.pseudo.key), p.pseudo.hit, p.pseudo.artifacts(),
                               f"pseudolabel/{p.label}" if state.multi else "pseudolabel")
