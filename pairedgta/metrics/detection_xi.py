"""Detection xi (this project's definition, docs/detection.md): per class and condition, the share of the reference
detector's confident clean boxes that the model still finds under the condition -- a box of the same class with
IoU >= `iou` and score >= the model's operating threshold, one match per box, greedy by score as COCO matches.
It is a recall: a detector that fires boxes everywhere keeps every reference box, so its precision side is kept
beside it (`precision`: the share of the model's confident boxes that match a reference box) and the
threshold-free pseudo-AP (pairedgta/metrics/coco_ap.py, the reference's boxes as ground truth).

Counts are kept per group (image) so the bootstrap resamples scenes, as segmentation's xi does."""
from __future__ import annotations

import numpy as np


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box of `a` (N x 4, xyxy) with every box of `b` (M x 4)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def match(ref_boxes: np.ndarray, ref_labels: np.ndarray, boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray,
          iou: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy one-to-one matching, highest score first: each box takes the unmatched reference box of its class
    with the highest IoU >= `iou`. Returns (reference box found, box matched) as boolean arrays."""
    found = np.zeros(len(ref_labels), bool)
    used = np.zeros(len(labels), bool)
    if not len(ref_labels) or not len(labels):
        return found, used
    overlap = box_iou(boxes, ref_boxes)
    overlap[np.asarray(labels)[:, None] != np.asarray(ref_labels)[None, :]] = 0.0
    for i in np.argsort(-np.asarray(scores), kind="stable"):
        cand = np.where(found, -1.0, overlap[i])
        j = int(cand.argmax())
        if cand[j] >= iou:
            found[j] = used[i] = True
    return found, used


def image_counts(ref_boxes: np.ndarray, ref_labels: np.ndarray, boxes: np.ndarray, scores: np.ndarray,
                 labels: np.ndarray, threshold: float, iou: float, num_classes: int) -> np.ndarray:
    """One image's counts per class (4 x C): reference boxes, those found, the model's confident boxes, those
    matching a reference box. Only boxes with score >= `threshold` (the model's operating point) take part."""
    keep = np.asarray(scores) >= threshold
    boxes, scores, labels = np.asarray(boxes).reshape(-1, 4)[keep], np.asarray(scores)[keep], np.asarray(labels)[keep]
    found, used = match(ref_boxes, ref_labels, boxes, scores, labels, iou)
    ref_labels = np.asarray(ref_labels, np.int64)
    labels = np.asarray(labels, np.int64)
    return np.stack([np.bincount(ref_labels, minlength=num_classes), np.bincount(ref_labels[found], minlength=num_classes),
                     np.bincount(labels, minlength=num_classes), np.bincount(labels[used], minlength=num_classes)])


def supported(refs: np.ndarray, min_boxes: int, min_images: int) -> np.ndarray:
    """Per class (refs: groups x C reference boxes): enough boxes in enough images to report xi (else NaN, marked)."""
    refs = np.asarray(refs)
    return (refs.sum(axis=0) >= min_boxes) & ((refs > 0).sum(axis=0) >= min_images)


def ratio(numer: np.ndarray, denom: np.ndarray) -> np.ndarray:
    """sum(numer) / sum(denom) per class over groups; NaN where the class has no denominator (never 0)."""
    n, d = np.asarray(numer, float).sum(axis=0), np.asarray(denom, float).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(d > 0, n / np.where(d > 0, d, 1), np.nan)


__all__ = ["box_iou", "image_counts", "match", "ratio", "supported"]
