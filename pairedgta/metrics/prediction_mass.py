"""phi^c, eq. (prediction_mass): pixels predicted as c with probability >= tau."""
from __future__ import annotations

import numpy as np

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none


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


def prediction_mass_from_labels(labels, confidence, num_classes: int, tau: float) -> torch.Tensor:
    """Same as `prediction_mass(probs, None, tau)` from (argmax labels, max probability): B x C counts."""
    labels = np.asarray(labels.numpy() if isinstance(labels, torch.Tensor) else labels).astype(np.int64, copy=False)
    conf = np.asarray(confidence.numpy() if isinstance(confidence, torch.Tensor) else confidence)
    if labels.ndim == 2:
        labels, conf = labels[None], conf[None]
    B = labels.shape[0]
    keyed = (labels + num_classes * np.arange(B).reshape(-1, 1, 1))[conf >= tau]
    return torch.from_numpy(np.bincount(keyed, minlength=num_classes * B).reshape(B, num_classes))
