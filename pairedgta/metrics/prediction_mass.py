"""phi^c, eq. (prediction_mass): pixels predicted as c with probability >= tau."""
from __future__ import annotations

import torch


def prediction_mass(probs: torch.Tensor, class_id: int | None, tau: float = 0.9) -> torch.Tensor:
    """probs: B x C x H x W (or C x H x W). Returns counts of shape B (or scalar), or B x C when
    `class_id` is None (every class at once, one pass)."""
    probs = torch.as_tensor(probs)
    squeeze = probs.ndim == 3
    if squeeze:
        probs = probs.unsqueeze(0)
    conf, labels = probs.max(dim=1)
    confident = conf >= tau  # argmax == c and P(c) >= tau  <=>  label == c and max prob >= tau
    if class_id is None:
        C = probs.shape[1]
        flat = (labels + C * torch.arange(labels.shape[0]).view(-1, 1, 1))[confident]
        counts = torch.bincount(flat, minlength=C * labels.shape[0]).view(labels.shape[0], C)
    else:
        counts = ((labels == class_id) & confident).flatten(1).sum(dim=1)
    return counts[0] if squeeze else counts


def prediction_mass_from_labels(labels: torch.Tensor, confidence: torch.Tensor, num_classes: int, tau: float) -> torch.Tensor:
    """Same as `prediction_mass(probs, None, tau)` from (argmax labels, max probability): B x C counts."""
    labels = torch.as_tensor(labels).long()
    if labels.ndim == 2:
        labels, confidence = labels.unsqueeze(0), torch.as_tensor(confidence).unsqueeze(0)
    confident = torch.as_tensor(confidence) >= tau
    B = labels.shape[0]
    flat = (labels + num_classes * torch.arange(B).view(-1, 1, 1))[confident]
    return torch.bincount(flat, minlength=num_classes * B).view(B, num_classes)
