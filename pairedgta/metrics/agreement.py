"""Pixel agreement on the pseudo-label's valid pixels: with the reference (pixel accuracy against the
pseudo-label) and with the model's own clean prediction (self-consistency under the shift).

Two aggregations over images (`aggregate_agreement`):
  "pooled"     sum of agreeing pixels / sum of valid pixels: every pixel weighs the same (the project's);
  "per_image"  mean of the per-image ratios: every image weighs the same (the authors' code).
Images without valid pixels drop out of the per-image mean (their ratio is 0/0)."""
from __future__ import annotations

import math

import numpy as np

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

AGREEMENT_MODES = ("pooled", "per_image")


def _np(x) -> np.ndarray:
    return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def pixel_agreement(a, b, reference_labels, ignore_index: int = 255) -> tuple[int, int]:
    """(agreeing pixels, valid pixels) of two label maps (arrays or tensors) where valid = reference is not void."""
    valid = _np(reference_labels) != ignore_index
    return int(((_np(a) == _np(b)) & valid).sum()), int(valid.sum())


def aggregate_agreement(agree, valid, mode: str = "pooled") -> float:
    """One agreement value from per-image (agreeing, valid) pixel counts; NaN without valid pixels."""
    if mode not in AGREEMENT_MODES:
        raise ValueError(f"unknown agreement aggregation {mode!r}; use one of {AGREEMENT_MODES}")
    agree, valid = np.asarray(agree, dtype=float), np.asarray(valid, dtype=float)
    if mode == "pooled":
        total = valid.sum()
        return float(agree.sum() / total) if total > 0 else math.nan
    some = valid > 0
    return float((agree[some] / valid[some]).mean()) if some.any() else math.nan
