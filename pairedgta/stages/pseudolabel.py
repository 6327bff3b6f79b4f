"""Pseudo-label stage: the reference model on each group's clean image; pixels with max softmax >= tau
keep their class, the rest become void (255). The paper's weak ground truth."""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
import pandas as pd

from pairedgta.datasets import LabelMaps, PairedDataset, load_image, load_label
from pairedgta.metrics import ConfusionMatrix
from pairedgta.models import shared_segmenter
from pairedgta.stages.common import Context, StageResult, Unsharded, model_hash_config, run_cached, torch_threads

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

log = logging.getLogger("pairedgta.pseudolabel")
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
    segmenter = shared_segmenter(model_cfg, device=ctx.run.device)
    maps = LabelMaps(out)
    hist = np.zeros(NUM_CLASSES, dtype=np.int64)
    total = 0
    gt_cm = ConfusionMatrix(NUM_CLASSES)
    gt_kept = gt_pixels = 0
    batch_size = ctx.run.pseudolabel.batch_size
    rows = []
    pending: list[tuple[str, np.ndarray]] = []

    def flush() -> None:
        nonlocal hist, total, gt_kept, gt_pixels
        if not pending:
            return
        stack = np.stack([im for _, im in pending])
        probs = segmenter.predict_proba(stack)
        labels = pseudo_label(probs, tau).to(torch.uint8).numpy()
        for (gid, _), lab in zip(pending, labels):
            maps.save(gid, lab)
            valid = lab != IGNORE_INDEX
            hist += np.bincount(lab[valid].astype(np.int64), minlength=NUM_CLASSES)
            total += lab.size
            rows.append({"group_id": gid, "valid_pixels": int(valid.sum()), "total_pixels": int(lab.size)})
            group = by_id[gid]
            if dataset.reference in group.labels:
                gt = load_label(group.labels[dataset.reference])
                gt_valid = gt != IGNORE_INDEX
                gt_pixels += int(gt_valid.sum())
                gt_kept += int((gt_valid & valid).sum())
                gt_cm.update(torch.from_numpy(np.where(valid, gt, IGNORE_INDEX)), torch.from_numpy(lab.astype(np.int64)))
        pending.clear()

    by_id = {g.group_id: g for g in dataset.groups}
    for group in tqdm(dataset.groups, desc=f"pseudolabel [{segmenter.name}]", unit="image"):
        image = load_image(group.images[dataset.reference])
        if pending and pending[0][1].shape != image.shape:
            flush()
        pending.append((group.group_id, image))
        if len(pending) >= batch_size:
            flush()
    flush()
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
    if gt_pixels:
        # how good is the paper's weak ground truth where the backend knows the truth
        iou = gt_cm.iou().numpy()
        with open(out / "quality.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["class_id", "class_name", "iou_on_kept_pixels"])
            for c in range(NUM_CLASSES):
                w.writerow([c, CLASS_NAMES[c], iou[c]])
        extra.update(accuracy_on_kept=gt_cm.accuracy(), coverage=gt_kept / gt_pixels, miou_on_kept=gt_cm.miou())
    return extra


@dataclass
class Pseudolabel(Unsharded):
    """The pseudo-label stage (pairedgta.stages.common.Stage) of one dataset and reference model."""

    ctx: Context
    dataset: PairedDataset
    dataset_key: str
    model_cfg: dict[str, Any]  # the reference model's composed config (the run's `reference_model`)
    name: str = "pseudolabel"
    version: str = VERSION
    resumable: bool = False
    result_cls: type[PseudoLabels] = PseudoLabels

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        return {"reference_model": model_hash_config(self.model_cfg), "tau": self.ctx.run.pseudolabel.tau,
                "reference": self.dataset.reference, "threads": self.ctx.run.threads}

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        with torch_threads(self.ctx.run.threads):
            return compute(self.ctx, self.dataset, out, self.model_cfg, self.ctx.run.pseudolabel.tau)


def run(ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any]) -> PseudoLabels:
    result = run_cached(ctx, Pseudolabel(ctx, dataset, dataset_key, model_cfg))
    assert isinstance(result, PseudoLabels)
    return result


def step(ctx: Context, p: Any, state: Any) -> None:
    """The app's step for one pass (pairedgta.stages.planning.PassResult, RunState): the reference model's
    pseudo-labels, their files in the run's MLflow record."""
    from pairedgta.tracking import bundle

    p.pseudo = run(ctx, p.dataset, p.dataset_key, state.models.reference)
    state.summary.setdefault("pseudolabel", str(p.pseudo.path))
    state.recorder.stage_files(bundle("pseudolabel", p.pseudo.key), p.pseudo.hit, p.pseudo.artifacts(),
                               f"pseudolabel/{p.label}" if state.multi else "pseudolabel")
