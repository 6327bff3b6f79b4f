"""Ground-truth metrics where the backend gives labels: per-class IoU from a streaming confusion matrix.
False positives count only on pixels whose ground truth is not void, as in cityscapesscripts."""
from __future__ import annotations

import numpy as np

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none


class ConfusionMatrix:
    def __init__(self, num_classes: int = 19, ignore_index: int = 255) -> None:
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self.mat = torch.zeros(num_classes, num_classes, dtype=torch.long)

    def update(self, target, pred) -> None:
        t = np.asarray(target.numpy() if isinstance(target, torch.Tensor) else target).astype(np.int64, copy=False).reshape(-1)
        p = np.asarray(pred.numpy() if isinstance(pred, torch.Tensor) else pred).astype(np.int64, copy=False).reshape(-1)
        valid = (t != self.ignore_index) & (t >= 0) & (t < self.num_classes) & (p >= 0) & (p < self.num_classes)
        idx = t[valid] * self.num_classes + p[valid]
        n = self.num_classes
        self.mat += torch.from_numpy(np.bincount(idx, minlength=n * n).reshape(n, n))

    def iou(self) -> torch.Tensor:
        """Per-class IoU; NaN for classes absent from both target and prediction."""
        m = self.mat.double()
        tp = m.diag()
        union = m.sum(0) + m.sum(1) - tp
        return torch.where(union > 0, tp / union.clamp_min(1), torch.full_like(tp, float("nan")))

    def miou(self) -> float:
        """Mean over the classes with TP + FP + FN > 0, as cityscapesscripts' evaluator averages (a class
        only predicted, never in the ground truth, counts with IoU 0; one in neither is left out)."""
        iou = self.iou()
        defined = ~torch.isnan(iou)
        return float(iou[defined].mean()) if defined.any() else float("nan")

    def accuracy(self) -> float:
        total = self.mat.sum()
        return float(self.mat.diag().sum() / total) if total > 0 else float("nan")
