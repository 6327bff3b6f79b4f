"""xi_c(i), eq. (class_reference_consistency): of the pixels the clean reference assigns to class c,
the share still predicted as c under condition i, pooled over all images (not averaged per image)."""
from __future__ import annotations

import numpy as np
import torch


def _np(x) -> np.ndarray:
    return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def reference_consistency_counts(
    reference_labels, predicted_labels, num_classes: int, ignore_index: int = 255
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-class (retained, reference) pixel counts of one batch; void reference pixels are excluded.

    One bincount over 2*C bins (class, agrees?) in numpy: ~100x faster on the CPU than torch masking."""
    ref = _np(reference_labels).astype(np.int64, copy=False).reshape(-1)
    pred = _np(predicted_labels).astype(np.int64, copy=False).reshape(-1)
    if ref.shape != pred.shape:
        raise ValueError(f"reference and prediction differ in size: {ref.shape} vs {pred.shape}")
    valid = (ref >= 0) & (ref < num_classes) & (ref != ignore_index)
    ref_v = ref[valid]
    counts = np.bincount(ref_v * 2 + (pred[valid] == ref_v), minlength=2 * num_classes).reshape(num_classes, 2)
    return torch.from_numpy(counts[:, 1].copy()), torch.from_numpy(counts.sum(axis=1))


class ReferenceConsistency:
    """Streaming xi: `update(reference_labels, predicted_labels)` adds counts, `compute()` divides.

    The torchmetrics update/compute contract with sum-reduced state, written out because importing
    torchmetrics costs seconds per CLI start; `merge` combines shards (e.g. per-process results).
    Classes without reference pixels are NaN (undefined, not zero)."""

    higher_is_better = True

    def __init__(self, num_classes: int = 19, ignore_index: int = 255) -> None:
        self.num_classes = int(num_classes)
        self.ignore_index = int(ignore_index)
        self.reset()

    def reset(self) -> None:
        self.retained = torch.zeros(self.num_classes, dtype=torch.long)
        self.reference = torch.zeros(self.num_classes, dtype=torch.long)

    def update(self, reference_labels: torch.Tensor, predicted_labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Add one batch; returns that batch's (retained, reference) counts for per-image statistics."""
        retained, reference = reference_consistency_counts(
            reference_labels, predicted_labels, self.num_classes, self.ignore_index
        )
        self.retained += retained
        self.reference += reference
        return retained, reference

    def merge(self, other: "ReferenceConsistency") -> "ReferenceConsistency":
        self.retained += other.retained
        self.reference += other.reference
        return self

    def compute(self) -> torch.Tensor:
        ref = self.reference.double()
        return torch.where(ref > 0, self.retained.double() / ref.clamp_min(1), torch.full_like(ref, float("nan")))

    def mean(self) -> float:
        """Class-wise mean over the classes that are defined (have reference pixels)."""
        xi = self.compute()
        defined = ~torch.isnan(xi)
        return float(xi[defined].mean()) if defined.any() else float("nan")
