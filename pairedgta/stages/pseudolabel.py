"""Pseudo-label stage: the reference model on each group's clean image; pixels with max softmax >= tau
keep their class, the rest become void (255). The paper's weak ground truth."""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
import pandas as pd

from pairedgta.datasets import LabelMaps, PairedDataset, load_image, load_label
from pairedgta.metrics import ConfusionMatrix
from pairedgta.models import shared_segmenter
from pairedgta.models.runtime import torch_threads
from pairedgta.stages.common import Context, StageResult, Unsharded, model_hash_config, run_cached

from pairedgta.lazy import lazy_module

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

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
    """The reference model on each group's reference image, batched; label map, class histogram and quality
    counts on the model's device; only the uint8 label maps and per-image counts cross to the host, read a
    batch later (while the next batch computes), and the finite-output check is read once, at the end."""
    from pairedgta.evaluation import reductions
    from pairedgta.models.base import to_device

    segmenter = shared_segmenter(model_cfg, device=ctx.run.device)
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


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass: the reference model's pseudo-labels, their files in the run's MLflow record."""
    from pairedgta.tracking import bundle

    p.pseudo = run_cached(ctx, Pseudolabel(ctx, p.dataset, p.dataset_key, state.models.reference))
    assert isinstance(p.pseudo, PseudoLabels)
    state.summary.setdefault("pseudolabel", str(p.pseudo.path))
    state.recorder.stage_files(bundle("pseudolabel", p.pseudo.key), p.pseudo.hit, p.pseudo.artifacts(),
                               f"pseudolabel/{p.label}" if state.multi else "pseudolabel")
