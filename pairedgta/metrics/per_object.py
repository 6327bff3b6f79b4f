"""Per object: the same object exists in every condition of a group (one instance id), so whether a model still
finds it can be followed along its size, the fog's transmittance over its pixels and the light on it (mean luma of
its box in that image): where does each model stop seeing a pedestrian? No benchmark of corrupted images can ask."""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import pandas as pd

from pairedgta.metrics.detection_xi import match

HEIGHT_BINS = (0, 16, 32, 64, 128, math.inf)
TRANSMITTANCE_BINS = (0.0, 0.05, 0.1, 0.2, 0.4, 0.7, 1.0001)
LUMA_BINS = (0.0, 0.05, 0.1, 0.2, 0.4, 1.0001)


def luma_in_boxes(image: np.ndarray, boxes: Sequence[Any]) -> list[float]:
    """Mean Rec. 601 luma (0..1) of the image inside each box."""
    out = []
    for b in boxes:
        x0, y0, x1, y1 = (int(round(v)) for v in b.xyxy)
        patch = image[max(y0, 0):max(y1, y0 + 1), max(x0, 0):max(x1, x0 + 1)].astype(np.float32)
        out.append(float((patch @ np.array([0.299, 0.587, 0.114], np.float32)).mean() / 255.0) if patch.size else math.nan)
    return out


def object_rows(group: str, condition: str, gt: Sequence[Any], lumas: Sequence[float], boxes: np.ndarray,
                scores: np.ndarray, labels: np.ndarray, threshold: float, iou: float, classes: Sequence[str]
                ) -> list[dict[str, Any]]:
    """One row per ground-truth object (ignore regions included, flagged) of one image: found or not by the model's
    confident boxes (same class, IoU >= iou, one match each)."""
    keep = np.asarray(scores) >= threshold
    ref = np.array([b.xyxy for b in gt], np.float64).reshape(-1, 4)
    found, _ = match(ref, np.array([b.label for b in gt], np.int64), np.asarray(boxes).reshape(-1, 4)[keep],
                     np.asarray(scores)[keep], np.asarray(labels)[keep], iou)
    return [{"group_id": group, "condition": condition, "instance": b.instance, "class_name": classes[b.label],
             "height": b.height, "area": b.area, "transmittance": b.transmittance, "luma": lum,
             "ignore": b.ignore, "truncated": b.truncated, "found": bool(f)}
            for b, lum, f in zip(gt, lumas, found)]


def found_share(rows: pd.DataFrame, by: str, bins: Sequence[float]) -> pd.DataFrame:
    """Share of scored objects found per condition, class (and "all") and bin of `by`; `objects` = the count."""
    scored = rows[(rows["ignore"] == "") & rows[by].notna()] if len(rows) else rows
    if not len(scored):
        return pd.DataFrame(columns=["condition", "class_name", "variable", "bin_low", "bin_high", "objects", "found"])
    scored = pd.concat([scored, scored.assign(class_name="all")])
    cut = pd.cut(scored[by], list(bins), right=False)
    g = scored.groupby(["condition", "class_name", cut], observed=True)["found"].agg(["size", "mean"]).reset_index()
    return pd.DataFrame({"condition": g["condition"], "class_name": g["class_name"], "variable": by,
                         "bin_low": [iv.left for iv in g[by]], "bin_high": [iv.right for iv in g[by]],
                         "objects": g["size"], "found": g["mean"]})


__all__ = ["HEIGHT_BINS", "LUMA_BINS", "TRANSMITTANCE_BINS", "found_share", "luma_in_boxes", "object_rows"]
