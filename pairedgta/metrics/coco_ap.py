"""COCO AP through pycocotools, the field's reference implementation (not a hand-written AP): AP@[.5:.95], AP50,
AP75 and per-class AP from COCOeval's accumulated precision at `max_detections` boxes per image. A class without
ground truth in the images is -1 in COCOeval and NaN here (it leaves the mean, as in COCO); a condition whose
images hold no scored object at all is NaN with that reason, nothing divides by zero."""
from __future__ import annotations

import contextlib
import io
import math
from typing import Any, Sequence

import numpy as np


def _coco(dataset: dict[str, Any]) -> Any:
    from pycocotools.coco import COCO

    coco = COCO()
    coco.dataset = dataset
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
    return coco


def average_precision(ground_truth: dict[str, Any], detections: Sequence[dict[str, Any]],
                      max_detections: int = 100, categories: Sequence[int] | None = None) -> dict[str, Any]:
    """`ground_truth`: a COCO dataset dict (images, annotations, categories); `detections`: COCO results
    (image_id, category_id, bbox xywh, score). Returns ap, ap50, ap75 and per_class {category_id: (ap, ap50)}.
    `categories`: the ones scored (a model that cannot predict a class is not averaged over it; its AP is NaN)."""
    from pycocotools.cocoeval import COCOeval

    cats = [c["id"] for c in ground_truth["categories"]]
    scored = set(cats if categories is None else categories)
    nan = {"ap": math.nan, "ap50": math.nan, "ap75": math.nan, "per_class": {c: (math.nan, math.nan) for c in cats}}
    if not any(not a.get("iscrowd") and a["category_id"] in scored for a in ground_truth["annotations"]):
        return {**nan, "reason": "no scored object in these images"}
    gt = _coco(ground_truth)
    image_ids = {im["id"] for im in ground_truth["images"]}
    dets = [dict(d, id=i + 1, area=float(d["bbox"][2] * d["bbox"][3]), iscrowd=0)
            for i, d in enumerate(detections) if d["image_id"] in image_ids]
    dt = _coco({"images": ground_truth["images"], "categories": ground_truth["categories"], "annotations": dets})
    ev = COCOeval(gt, dt, iouType="bbox")
    ev.params.maxDets = [1, 10, int(max_detections)]
    ev.params.catIds = [c for c in cats if c in scored]
    ev.params.areaRng, ev.params.areaRngLbl = [[0, 1e10]], ["all"]  # only "all" is reported: a quarter of the work
    with contextlib.redirect_stdout(io.StringIO()):
        ev.evaluate()
        ev.accumulate()
    p = ev.eval["precision"][:, :, :, 0, -1]  # T x R x K at all areas, max_detections

    def mean(a: np.ndarray) -> float:
        a = a[a > -1]
        return float(a.mean()) if a.size else math.nan

    t50, t75 = int(np.argmin(abs(ev.params.iouThrs - 0.5))), int(np.argmin(abs(ev.params.iouThrs - 0.75)))
    per_class = {c: (math.nan, math.nan) for c in cats}
    per_class.update({c: (mean(p[:, :, k]), mean(p[t50, :, k])) for k, c in enumerate(ev.params.catIds)})
    return {"ap": mean(p), "ap50": mean(p[t50]), "ap75": mean(p[t75]), "per_class": per_class}


def results_format(image_id: int, boxes: np.ndarray, scores: np.ndarray, category_ids: np.ndarray,
                   max_detections: int = 100) -> list[dict[str, Any]]:
    """One image's detections in COCO results format (bbox xywh), the `max_detections` highest scores."""
    order = np.argsort(-np.asarray(scores), kind="stable")[:max_detections]
    return [{"image_id": int(image_id), "category_id": int(category_ids[i]),
             "bbox": [round(float(boxes[i, 0]), 2), round(float(boxes[i, 1]), 2),
                      round(float(boxes[i, 2] - boxes[i, 0]), 2), round(float(boxes[i, 3] - boxes[i, 1]), 2)],
             "score": round(float(scores[i]), 5)} for i in order]


__all__ = ["average_precision", "results_format"]
