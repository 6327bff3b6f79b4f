"""Ground-truth metrics where the backend gives labels: per-class IoU from a streaming confusion matrix.
False positives count only on pixels whose ground truth is not void, as in cityscapesscripts."""
from __future__ import annotations

import numpy as np

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none


def confusion_counts(target, pred, num_classes: int, ignore_index: int = 255) -> np.ndarray:
    """One batch's confusion matrix (truth x prediction, int64); void truth and out-of-range labels are left out."""
    t = np.asarray(target.numpy() if isinstance(target, torch.Tensor) else target).astype(np.int64, copy=False).reshape(-1)
    p = np.asarray(pred.numpy() if isinstance(pred, torch.Tensor) else pred).astype(np.int64, copy=False).reshape(-1)
    valid = (t != ignore_index) & (t >= 0) & (t < num_classes) & (p >= 0) & (p < num_classes)
    idx = t[valid] * num_classes + p[valid]
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


class ConfusionMatrix:
    """Streaming IoU, the torchmetrics update/compute contract: `update(target, pred)` adds a batch,
    `update_counts(matrix)` adds one counted elsewhere (a group's matrix from evaluate's group counts)."""

    def __init__(self, num_classes: int = 19, ignore_index: int = 255) -> None:
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self.mat = torch.zeros(num_classes, num_classes, dtype=torch.long)

    def update(self, target, pred) -> None:
        self.update_counts(confusion_counts(target, pred, self.num_classes, self.ignore_index))

    def update_counts(self, matrix) -> None:
        counts = torch.as_tensor(np.asarray(matrix, dtype=np.int64))
        if counts.shape != self.mat.shape:
            raise ValueError(f"confusion matrix of shape {tuple(counts.shape)}; this metric counts {tuple(self.mat.shape)}")
        self.mat += counts

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
