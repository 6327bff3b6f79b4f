"""COCO AP on scene resamples: pycocotools matches every image once (COCOeval.evaluate, the reference
implementation's per-image matching), and its accumulation is redone here with a weight per image, for many
weightings at once. A bootstrap draw that takes an image k times is a weight of k: the AP equals pycocotools' on the
images repeated k times (tests/test_detection_study.py checks the all-ones weighting against COCOeval.summarize's AP
and a repeated draw against COCOeval on the repeated images). Only the "all" area range, at max_detections.

Why not COCOeval per resample: 1000 resamples x detectors x conditions of pycocotools' accumulate in Python loops
take hours; the weighted cumulative sums here take seconds."""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

REC_THRS = np.linspace(0.0, 1.00, 101)


@dataclass
class PerImage:
    """One condition's matches: per category, its detections sorted by score over every image (COCO's order),
    their image index, their match per IoU threshold (T x D) and ignore flags, and per image the number of
    non-ignored ground-truth objects."""

    iou_thrs: np.ndarray
    images: list[int]  # COCO image ids, the order of the weights
    categories: list[int]
    det_image: list[np.ndarray]  # per category: D image indices
    tp: list[np.ndarray]  # per category: T x D (matched and not ignored)
    fp: list[np.ndarray]  # per category: T x D (unmatched and not ignored)
    gt_count: np.ndarray  # K x N: non-ignored ground truth per category and image


def match(ground_truth: dict[str, Any], detections: Sequence[dict[str, Any]], max_detections: int = 100,
          iou_thrs: Sequence[float] | None = None, categories: Sequence[int] | None = None) -> PerImage:
    """pycocotools' per-image matching of `detections` against `ground_truth` (COCO dicts)."""
    from pycocotools.cocoeval import COCOeval

    from pairedgta.metrics.coco_ap import _coco as coco

    image_ids = [im["id"] for im in ground_truth["images"]]
    dets = [dict(d, id=i + 1, area=float(d["bbox"][2] * d["bbox"][3]), iscrowd=0)
            for i, d in enumerate(detections) if d["image_id"] in set(image_ids)]
    gt = coco(ground_truth)
    dt = coco({"images": ground_truth["images"], "categories": ground_truth["categories"], "annotations": dets})
    ev = COCOeval(gt, dt, iouType="bbox")
    ev.params.imgIds = image_ids
    ev.params.maxDets = [1, 10, int(max_detections)]
    ev.params.areaRng, ev.params.areaRngLbl = [[0, 1e10]], ["all"]
    if iou_thrs is not None:
        ev.params.iouThrs = np.asarray(iou_thrs, float)
    cats = [c["id"] for c in ground_truth["categories"]] if categories is None else list(categories)
    ev.params.catIds = cats
    with contextlib.redirect_stdout(io.StringIO()):
        ev.evaluate()
    n_img, t = len(image_ids), len(ev.params.iouThrs)
    index = {iid: i for i, iid in enumerate(image_ids)}
    det_image, tp, fp = [], [], []
    gt_count = np.zeros((len(cats), n_img))
    for k in range(len(cats)):
        entries = ev.evalImgs[k * n_img:(k + 1) * n_img]  # one area range: catId-major, image-minor
        scores, imgs, matched, ignored = [], [], [], []
        for e in entries:
            if e is None:
                continue
            i = index[e["image_id"]]
            gt_count[k, i] = int(np.count_nonzero(e["gtIgnore"] == 0))
            d = e["dtScores"][:max_detections]
            scores.append(np.asarray(d, float))
            imgs.append(np.full(len(d), i))
            matched.append(np.asarray(e["dtMatches"])[:, :max_detections].reshape(t, -1))
            ignored.append(np.asarray(e["dtIgnore"])[:, :max_detections].reshape(t, -1))
        if scores:
            s = np.concatenate(scores)
            order = np.argsort(-s, kind="mergesort")  # COCOeval.accumulate's order
            m = np.concatenate(matched, axis=1)[:, order]
            ig = np.concatenate(ignored, axis=1)[:, order].astype(bool)
            det_image.append(np.concatenate(imgs)[order])
            tp.append(np.logical_and(m, ~ig).astype(float))
            fp.append(np.logical_and(np.logical_not(m), ~ig).astype(float))
        else:
            det_image.append(np.zeros(0, int))
            tp.append(np.zeros((t, 0)))
            fp.append(np.zeros((t, 0)))
    return PerImage(np.asarray(ev.params.iouThrs, float), image_ids, cats, det_image, tp, fp, gt_count)


def average_precision(m: PerImage, weights: np.ndarray, chunk: int = 64) -> np.ndarray:
    """R x N image weights -> R APs (COCO's 101-point interpolation, averaged over the IoU thresholds and the
    categories with ground truth in that resample, as COCOeval.summarize; NaN where none has)."""
    w = np.atleast_2d(np.asarray(weights, float))
    r_all, t = w.shape[0], len(m.iou_thrs)
    out = np.full(r_all, np.nan)
    for start in range(0, r_all, chunk):
        wr = w[start:start + chunk]
        r = len(wr)
        total = np.zeros(r)
        count = np.zeros(r)
        for k in range(len(m.categories)):
            npig = wr @ m.gt_count[k]  # R
            has = npig > 0
            d = m.det_image[k]
            if len(d) == 0:
                count += has * t * len(REC_THRS)  # precision 0 at every recall: counted, adds nothing
                continue
            wd = wr[:, d]  # R x D
            tp = np.cumsum(wd[:, None, :] * m.tp[k][None], axis=2)  # R x T x D
            fp = np.cumsum(wd[:, None, :] * m.fp[k][None], axis=2)
            with np.errstate(invalid="ignore", divide="ignore"):
                rc = tp / np.where(has, npig, 1.0)[:, None, None]
                pr = tp / (fp + tp + np.spacing(1))
            pr = np.maximum.accumulate(pr[:, :, ::-1], axis=2)[:, :, ::-1]  # the envelope: max to the right
            rows = rc.reshape(-1, rc.shape[-1])
            n_rows, n_det = rows.shape
            offset = 2.0 * np.arange(n_rows)[:, None]
            idx = np.searchsorted((rows + offset).ravel(), (REC_THRS[None, :] + offset).ravel(), side="left")
            idx = idx.reshape(n_rows, -1) - n_det * np.arange(n_rows)[:, None]
            inside = idx < n_det
            q = np.where(inside, np.take_along_axis(pr.reshape(n_rows, -1), np.minimum(idx, n_det - 1), axis=1), 0.0)
            q = q.reshape(r, t, -1)
            total += np.where(has, q.sum(axis=(1, 2)), 0.0)
            count += has * t * len(REC_THRS)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[start:start + r] = np.where(count > 0, total / np.where(count > 0, count, 1), np.nan)
    return out


__all__ = ["PerImage", "REC_THRS", "average_precision", "match"]
