"""xi_c(i), eq. (class_reference_consistency): of the pixels the clean reference assigns to class c,
the share still predicted as c under condition i, pooled over all images (not averaged per image).

Two conventions for a class without reference pixels (`absent`), because the paper's numbers and a
strict reading of its equation differ there:
  "nan"   undefined (0/0), left out of the class-wise mean: the project's strict convention;
  "zero"  the authors' code, which divides by max(reference pixels, 1): the class scores 0 and the
          class-wise mean (over a fixed class list) includes that 0. Table 1 is computed this way.

xi is a recall: a model that paints one class everywhere keeps every reference pixel of that class (xi_c = 1).
Its precision counterpart (`precision_from_counts`) is, per class c, the share of the valid reference pixels
(the same mask xi counts: not void, visible) that the model predicts as c whose reference is c, and the F-like
combination (`f_from_counts`) their harmonic mean; both from per-class counts, as xi is."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

ABSENT_POLICIES = ("nan", "zero")


def _np(x) -> np.ndarray:
    return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def check_absent(absent: str) -> str:
    if absent not in ABSENT_POLICIES:
        raise ValueError(f"unknown absent-class policy {absent!r}; use one of {ABSENT_POLICIES}")
    return absent


def xi_from_counts(retained, reference, absent: str = "nan") -> np.ndarray:
    """retained / reference elementwise (any shape); a zero reference gives NaN or 0 per `absent`."""
    check_absent(absent)
    ret = np.asarray(_np(retained), dtype=float)
    ref = np.asarray(_np(reference), dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = ret / np.maximum(ref, 1.0)  # the authors' clamp; identical to ret/ref wherever ref > 0
    return np.where(ref > 0, ratio, 0.0 if absent == "zero" else np.nan)


def precision_from_counts(retained, predicted, absent: str = "nan") -> np.ndarray:
    """xi's precision counterpart, retained / predicted elementwise: of the valid reference pixels the model predicts
    as class c, the share whose reference is c. A class the model never predicts on valid pixels (predicted 0) is
    undefined: NaN, or 0 under absent="zero", as xi treats a class without reference pixels."""
    return xi_from_counts(retained, predicted, absent)


def f_from_counts(retained, reference, predicted, absent: str = "nan") -> np.ndarray:
    """The harmonic mean of xi and its precision per class, from the counts: 2 retained / (reference + predicted)
    (the Dice of class c on the valid reference pixels). It equals 2 xi p / (xi + p) wherever both are defined and
    positive, and is 0 where nothing of the class is retained, also where the precision is undefined (a class never
    predicted: xi 0); undefined (NaN, or 0 under absent="zero") only where neither side has the class."""
    ret = np.asarray(_np(retained), dtype=float)
    both = np.asarray(_np(reference), dtype=float) + np.asarray(_np(predicted), dtype=float)
    return xi_from_counts(2.0 * ret, both, absent)


def mean_mask(num_classes: int, class_names: Iterable[str] | None = None, exclude: Iterable[str] = ()) -> np.ndarray:
    """Which classes enter the class-wise mean: every class but the `exclude`d names (the paper drops
    bus and train, which GTA V's pseudo-labels barely contain)."""
    names = list(class_names) if class_names is not None else [str(k) for k in range(num_classes)]
    if len(names) != num_classes:
        raise ValueError(f"{len(names)} class names for {num_classes} classes")
    excluded = set(exclude)
    unknown = excluded - set(names)
    if unknown:
        raise ValueError(f"mean_exclude: unknown class(es) {sorted(unknown)}")
    return np.array([n not in excluded for n in names])


def class_mean(xi, include=None) -> float:
    """Mean of xi over the included classes, skipping NaN (undefined) ones; NaN if none is left.
    Under absent="zero" no class is NaN, so the zeros of absent classes count."""
    xi = np.asarray(_np(xi), dtype=float)
    keep = np.ones(xi.shape[-1], bool) if include is None else np.asarray(include, bool)
    vals = xi[..., keep]
    vals = vals[~np.isnan(vals)]
    return float(vals.mean()) if vals.size else float("nan")


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


def predicted_counts(reference_labels, predicted_labels, num_classes: int, ignore_index: int = 255) -> np.ndarray:
    """Per class, the pixels predicted as that class among the valid reference pixels (those xi counts: void
    reference pixels excluded): the denominator of `precision_from_counts`, beside `reference_consistency_counts`."""
    ref = _np(reference_labels).astype(np.int64, copy=False).reshape(-1)
    pred = _np(predicted_labels).astype(np.int64, copy=False).reshape(-1)
    if ref.shape != pred.shape:
        raise ValueError(f"reference and prediction differ in size: {ref.shape} vs {pred.shape}")
    valid = (ref >= 0) & (ref < num_classes) & (ref != ignore_index)
    pred_v = pred[valid]
    pred_v = pred_v[(pred_v >= 0) & (pred_v < num_classes)]
    return np.bincount(pred_v, minlength=num_classes)[:num_classes]


class ReferenceConsistency:
    """Streaming xi: `update(reference_labels, predicted_labels)` adds counts, `compute()` divides.

    The torchmetrics update/compute contract with sum-reduced state, written out because importing
    torchmetrics costs seconds per CLI start; `merge` combines shards (e.g. per-process results).
    Classes without reference pixels are NaN (absent="nan", undefined) or 0 (absent="zero", the
    authors' convention)."""

    higher_is_better = True

    def __init__(self, num_classes: int = 19, ignore_index: int = 255, absent: str = "nan") -> None:
        self.num_classes = int(num_classes)
        self.ignore_index = int(ignore_index)
        self.absent = check_absent(absent)
        self.reset()

    def reset(self) -> None:
        self.retained = torch.zeros(self.num_classes, dtype=torch.long)
        self.reference = torch.zeros(self.num_classes, dtype=torch.long)

    def update(self, reference_labels: torch.Tensor, predicted_labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Add one batch; returns that batch's (retained, reference) counts for per-image statistics."""
        retained, reference = reference_consistency_counts(
            reference_labels, predicted_labels, self.num_classes, self.ignore_index
        )
        self.update_counts(retained, reference)
        return retained, reference

    def update_counts(self, retained, reference) -> None:
        """Add per-class counts taken elsewhere (one image's, from evaluate's group counts or a shard job)."""
        retained, reference = torch.as_tensor(_np(retained).astype(np.int64)), torch.as_tensor(_np(reference).astype(np.int64))
        if retained.shape != (self.num_classes,) or reference.shape != (self.num_classes,):
            raise ValueError(f"counts of shape {tuple(retained.shape)} and {tuple(reference.shape)}; this metric "
                             f"counts {self.num_classes} classes")
        self.retained += retained
        self.reference += reference

    def merge(self, other: "ReferenceConsistency") -> "ReferenceConsistency":
        self.retained += other.retained
        self.reference += other.reference
        return self

    def compute(self) -> torch.Tensor:
        return torch.from_numpy(xi_from_counts(self.retained, self.reference, self.absent))

    def mean(self, include=None) -> float:
        """Class-wise mean over the included classes (all by default): over the defined ones under
        absent="nan", with the absent ones as 0 under absent="zero"."""
        return class_mean(self.compute(), include)
