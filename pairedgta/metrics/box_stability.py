"""Two label-free estimators of a detector's accuracy that need a second look inside the network
(docs/detection.md "Is detection xi the best label-free judge?"; the study: pairedgta/metrics/detection_study.py).

- BoS, box stability (ICLR 2024, arXiv 2403.13803): the detector is run again with dropout (p = 0.15) on its
  backbone's features; the two sets of boxes (scored >= 0.05, the ones COCO AP scores) are matched one to one
  (Hungarian, cost -IoU, same class); per image, the sum of the matched IoUs over the smaller set's size (NaN when neither has a box, 0 when only one
  has). A detector that knows what it sees keeps its boxes when its features are perturbed.
- Pre-NMS consistency (PCR-style; ICCV 2025, arXiv 2508.12082 uses pre-NMS candidates and their confidences): the
  detector is run again without suppression; per final box (>= 0.05), the score-weighted mean IoU of the
  candidates of its class that collapse into it (IoU >= the suppression threshold); per image the mean over its
  boxes (NaN without one). Candidates that agree on where an object is make tight clusters.

Both run only where the network is a torch module with a backbone (BoS) or a suppression threshold (torchvision's
detection heads); elsewhere NaN, said in the study. `feature_dropout` and `no_suppression` are the two hooks."""
from __future__ import annotations

import contextlib
import math
from typing import Any, Iterator

import numpy as np

from pairedgta.metrics.detection_xi import box_iou

DROPOUT = 0.15
CANDIDATE_FLOOR = 0.05  # the candidates a suppression would weigh (torchvision's score floor)


def box_stability(boxes_a: np.ndarray, labels_a: np.ndarray, boxes_b: np.ndarray, labels_b: np.ndarray) -> float:
    """Sum of the Hungarian-matched IoUs (same class) over min(|A|, |B|); NaN for two empty sets, 0 for one."""
    from scipy.optimize import linear_sum_assignment

    na, nb = len(labels_a), len(labels_b)
    if na == 0 and nb == 0:
        return math.nan
    if na == 0 or nb == 0:
        return 0.0
    iou = box_iou(boxes_a, boxes_b)
    iou[np.asarray(labels_a)[:, None] != np.asarray(labels_b)[None, :]] = 0.0
    rows, cols = linear_sum_assignment(-iou)
    return float(iou[rows, cols].sum() / min(na, nb))


def cluster_consistency(final_boxes: np.ndarray, final_labels: np.ndarray, cand_boxes: np.ndarray,
                        cand_scores: np.ndarray, cand_labels: np.ndarray, iou: float) -> float:
    """Mean over the final boxes of the score-weighted mean IoU of their class's candidates with IoU >= `iou`
    (the candidates that suppression collapses into it); NaN without a final box."""
    if not len(final_labels):
        return math.nan
    keep = np.asarray(cand_scores) >= CANDIDATE_FLOOR
    cb, cs, cl = np.asarray(cand_boxes).reshape(-1, 4)[keep], np.asarray(cand_scores)[keep], np.asarray(cand_labels)[keep]
    overlap = box_iou(final_boxes, cb)
    overlap[np.asarray(final_labels)[:, None] != cl[None, :]] = 0.0
    values = []
    for row in overlap:
        members = row >= iou
        values.append(float((cs[members] * row[members]).sum() / cs[members].sum()) if members.any() else 0.0)
    return float(np.mean(values))


def _module(detector: Any) -> Any:
    module = getattr(detector, "module", None)
    return getattr(module, "module", module)  # a ContractDetector's network may wrap the torchvision model


@contextlib.contextmanager
def feature_dropout(detector: Any, p: float = DROPOUT, seed: int = 0) -> Iterator[bool]:
    """Inside: the detector's backbone features pass through dropout (a fixed seed); yields whether it could."""
    import torch

    module = _module(detector)
    backbone = getattr(module, "backbone", None)
    if backbone is None or not hasattr(backbone, "register_forward_hook"):
        yield False
        return
    gen = torch.Generator(device="cpu").manual_seed(int(seed))

    def drop(x: torch.Tensor) -> torch.Tensor:
        mask = (torch.rand(x.shape, generator=gen) >= p).to(x.device, x.dtype) / (1.0 - p)
        return x * mask

    def hook(_mod: Any, _inp: Any, out: Any) -> Any:
        if isinstance(out, dict):
            return type(out)((k, drop(v)) for k, v in out.items())
        return drop(out) if isinstance(out, torch.Tensor) else out

    handle = backbone.register_forward_hook(hook)
    try:
        yield True
    finally:
        handle.remove()


def _suppressors(module: Any) -> list[tuple[Any, str]]:
    found = [(module, "nms_thresh")] if hasattr(module, "nms_thresh") else []
    heads = getattr(module, "roi_heads", None)
    if heads is not None and hasattr(heads, "nms_thresh"):
        found.append((heads, "nms_thresh"))
    return found


@contextlib.contextmanager
def no_suppression(detector: Any) -> Iterator[float | None]:
    """Inside: the detector's NMS keeps every candidate (threshold 1.0, up to 1000 an image); yields the threshold
    it had (the clusters' IoU), None where it has none reachable."""
    module = _module(detector)
    places = _suppressors(module)
    if not places:
        yield None
        return
    saved = [(obj, attr, getattr(obj, attr)) for obj, attr in places]
    caps = [(obj, attr, getattr(obj, attr)) for obj in (module, getattr(module, "roi_heads", None)) if obj is not None
            for attr in ("detections_per_img",) if hasattr(obj, attr)]
    try:
        for obj, attr, _ in saved:
            setattr(obj, attr, 1.0)
        for obj, attr, _ in caps:
            setattr(obj, attr, 1000)
        yield float(saved[-1][2])
    finally:
        for obj, attr, value in saved + caps:
            setattr(obj, attr, value)


def image_estimators(detector: Any, image: np.ndarray, final: Any, threshold: float = CANDIDATE_FLOOR,
                     seed: int = 0) -> dict[str, float]:
    """BoS and the pre-NMS consistency of one image (`final`: its Detections as evaluated), over its boxes scored
    >= `threshold`: by default the ones COCO AP scores (>= 0.05, at most 100), so that a detector whose operating
    threshold leaves an image empty still has a value."""
    confident = final.above(threshold)
    out = {"bos": math.nan, "pcr": math.nan}
    with feature_dropout(detector, seed=seed) as ok:
        if ok:
            (dropped,) = detector.detect(image[None])
            d = dropped.above(threshold)
            out["bos"] = box_stability(confident.boxes, confident.labels, d.boxes, d.labels)
    with no_suppression(detector) as iou:
        if iou is not None:
            (cands,) = detector.detect(image[None])
            out["pcr"] = cluster_consistency(confident.boxes, confident.labels, cands.boxes, cands.scores,
                                             cands.labels, iou)
    return out


__all__ = ["CANDIDATE_FLOOR", "DROPOUT", "box_stability", "cluster_consistency", "feature_dropout",
           "image_estimators", "no_suppression"]
