"""Pixel agreement on the pseudo-label's valid pixels: with the reference (pixel accuracy against the
pseudo-label) and with the model's own clean prediction (self-consistency under the shift)."""
from __future__ import annotations

import torch


def pixel_agreement(a: torch.Tensor, b: torch.Tensor, reference_labels: torch.Tensor, ignore_index: int = 255) -> tuple[int, int]:
    """(agreeing pixels, valid pixels) where valid = reference is not void."""
    a, b = torch.as_tensor(a), torch.as_tensor(b)
    valid = torch.as_tensor(reference_labels) != ignore_index
    return int(((a == b) & valid).sum()), int(valid.sum())
