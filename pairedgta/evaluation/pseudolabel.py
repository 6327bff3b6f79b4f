"""Segmentation's pseudo-labels (the work of the `pseudolabel` stage for task=segmentation): the reference model on
each group's clean image; pixels with max softmax >= tau keep their class, the rest become void (255). The paper's
weak ground truth, with its quality against the renderer's labels where the backend knows them."""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import LabelMaps, PairedDataset, load_image, load_label
from pairedgta.entries import Context, StageResult, model_hash_config
from pairedgta.lazy import lazy_module
from pairedgta.metrics import ConfusionMatrix
from pairedgta.models import shared_model
from pairedgta.work import Work

torch = lazy_module("torch")  # imported on first use: a cached run needs none

VERSION = "2"  # 2: miou_on_kept in the Cityscapes convention (classes with TP + FP + FN > 0)


class PseudoLabels(StageResult):
    """The pseudo-label stage's entry: one label map per group, the class histogram, quality vs truth."""

    @property
    def labels(self) -> LabelMaps:
        return LabelMaps(self.path)

    def histogram(self) -> pd.DataFrame:
        return pd.read_csv(self.path / "histogram.csv")

    def index(self) -> pd.DataFrame:
        """Per group: valid (non-void) and total pixels of its pseudo-label."""
        return pd.read_csv(self.path / "index.csv", dtype={"group_id": str})

    def reference_model(self) -> str:
        return str(self.manifest()["config"]["reference_model"]["name"])

    def tau(self) -> float:
        return float(self.manifest()["config"]["tau"])

    def artifacts(self) -> list[Path]:
        return [p for p in (self.path / "histogram.csv", self.path / "quality.csv") if p.is_file()]


def pseudo_label(probs: torch.Tensor, tau: float) -> torch.Tensor:
    conf, labels = probs.max(dim=1)
    return torch.where(conf >= tau, labels, torch.full_like(labels, IGNORE_INDEX))


def compute(ctx: Context, dataset: PairedDataset, out: Path, model_cfg: dict[str, Any], tau: float) -> dict[str, Any]:
    """The reference model on each group's reference image, batched; label map, class histogram and quality
    counts on the model's device; only the uint8 label maps and per-image counts cross to the host, read a
    batch later (while the next batch computes), and the finite-output check is read once, at the end."""
    from pairedgta.evaluation import reductions
    from pairedgta.models.base import to_device

    segmenter = shared_model(model_cfg, device=ctx.run.device)
    device = segmenter.device
    maps = LabelMaps(out)
    hist = torch.zeros(NUM_CLASSES, dtype=torch.int64, device=device)
    gt_counts = torch.zeros(NUM_CLASSES * NUM_CLASSES + 2, dtype=torch.int64, device=device)  # matrix, kept, pixels
    seen_gt = False
    total = 0
    batch_size = ctx.run.pseudolabel.batch_size
    rows = []
    pending: list[tuple[str, np.ndarray]] = []
    waiting: list[tuple[list[str], reductions.HostCopy]] = []

    def launch() -> None:
        nonlocal hist, gt_counts, seen_gt
        if not pending:
            return
        with torch.inference_mode():
            m = segmenter.predict_maps(np.stack([im for _, im in pending]), entropy=False)
            void = torch.full((), IGNORE_INDEX, dtype=m.labels.dtype, device=device)
            labels = torch.where(m.confidence >= tau, m.labels, void).to(torch.uint8)
            valid = labels != IGNORE_INDEX
            hist += reductions.class_counts(labels, valid).sum(dim=0)
            for i, (gid, _) in enumerate(pending):
                group = by_id[gid]
                if dataset.reference in group.labels:  # how good is the weak ground truth where the truth is known
                    seen_gt = True
                    gt = np.array(load_label(group.labels[dataset.reference]), np.uint8)  # train ids: 0-18, 255
                    gt = to_device(torch.from_numpy(gt), device)
                    gt_valid = gt != IGNORE_INDEX
                    cm = reductions.confusion(torch.where(valid[i], gt, void)[None], labels[i][None])[0]
                    gt_counts += torch.cat([cm.reshape(-1), (gt_valid & valid[i]).sum().view(1), gt_valid.sum().view(1)])
            copy = reductions.HostCopy({"labels": labels, "valid": valid.sum(dim=(1, 2))})
        waiting.append(([gid for gid, _ in pending], copy))
        pending.clear()

    def finish() -> None:
        nonlocal total
        gids, copy = waiting.pop(0)
        r = copy.get()
        for gid, lab, valid in zip(gids, r["labels"], r["valid"]):
            maps.save(gid, lab)
            total += lab.size
            rows.append({"group_id": gid, "valid_pixels": int(valid), "total_pixels": int(lab.size)})

    by_id = {g.group_id: g for g in dataset.groups}
    for group in tqdm(dataset.groups, desc=f"pseudolabel [{segmenter.name}]", unit="image"):
        image = load_image(group.images[dataset.reference])
        if pending and pending[0][1].shape != image.shape:
            launch()
        pending.append((group.group_id, image))
        if len(pending) >= batch_size:
            launch()
        while len(waiting) > 1:  # the batch before the one the device works on
            finish()
    launch()
    while waiting:
        finish()
    segmenter.check_finite()
    hist = hist.cpu().numpy()
    with open(out / "index.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["group_id", "valid_pixels", "total_pixels"])
        w.writeheader()
        w.writerows(rows)
    with open(out / "histogram.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["class_id", "class_name", "pixels", "share_of_valid", "share_of_all"])
        valid_total = max(int(hist.sum()), 1)
        for c in range(NUM_CLASSES):
            w.writerow([c, CLASS_NAMES[c], int(hist[c]), hist[c] / valid_total, hist[c] / max(total, 1)])
    extra: dict[str, Any] = {"groups": len(rows), "void_share": 1 - hist.sum() / max(total, 1)}
    counts = gt_counts.cpu().numpy()
    gt_kept, gt_pixels = int(counts[-2]), int(counts[-1])
    if seen_gt and gt_pixels:
        gt_cm = ConfusionMatrix(NUM_CLASSES)
        gt_cm.update_counts(counts[:-2].reshape(NUM_CLASSES, NUM_CLASSES))
        # how good is the paper's weak ground truth where the backend knows the truth
        iou = gt_cm.iou().numpy()
        with open(out / "quality.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["class_id", "class_name", "iou_on_kept_pixels"])
            for c in range(NUM_CLASSES):
                w.writerow([c, CLASS_NAMES[c], iou[c]])
        extra.update(accuracy_on_kept=gt_cm.accuracy(), coverage=gt_kept / gt_pixels, miou_on_kept=gt_cm.miou())
    return extra


@dataclass(frozen=True)
class SegmentationPseudolabels(Work):
    """The `pseudolabel` stage's work for segmentation (pairedgta.work.PseudolabelWork)."""

    ENTRY_VERSION: ClassVar[str] = VERSION
    result_cls: type[PseudoLabels] = PseudoLabels

    def hash_config(self, ctx: Context, dataset: PairedDataset, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return {"reference_model": model_hash_config(model_cfg), "tau": ctx.run.pseudolabel.tau,
                "reference": dataset.reference, "threads": ctx.run.threads}

    def compute(self, ctx: Context, dataset: PairedDataset, out: Path, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return compute(ctx, dataset, out, model_cfg, ctx.run.pseudolabel.tau)


__all__ = ["PseudoLabels", "SegmentationPseudolabels", "compute", "pseudo_label"]
