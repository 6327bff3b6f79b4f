"""Is detection xi the best label-free judge? (pairedgta/metrics/detection_study.py, coco_resample.py,
box_stability.py): COCO AP on weighted scenes equals pycocotools' on the repeated images; BoS and the pre-NMS
consistency on hand-made boxes; the study's statistics on a fixed case."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pairedgta.metrics import coco_ap, coco_resample


def random_case(seed: int, n_images: int = 6, classes: int = 3):
    """Ground truth and detections with hits, misses, duplicates, crowd regions and a class without objects."""
    rng = np.random.default_rng(seed)
    images, anns, dets = [], [], []
    for i in range(1, n_images + 1):
        images.append({"id": i, "width": 200, "height": 100})
        for _ in range(int(rng.integers(0, 5))):
            x, y, w, h = rng.uniform(0, 150), rng.uniform(0, 60), rng.uniform(8, 50), rng.uniform(8, 40)
            cat = int(rng.integers(1, classes))  # the last class never has ground truth
            anns.append({"id": len(anns) + 1, "image_id": i, "category_id": cat, "bbox": [x, y, w, h], "area": w * h,
                         "iscrowd": int(rng.random() < 0.1)})
            for _ in range(int(rng.integers(0, 3))):
                j = rng.normal(0, 4, 4)
                dets.append({"image_id": i, "category_id": cat, "bbox": [x + j[0], y + j[1], max(2, w + j[2]),
                                                                          max(2, h + j[3])],
                             "score": float(rng.uniform(0.05, 1))})
        for _ in range(int(rng.integers(0, 4))):  # false positives, some of the last class
            dets.append({"image_id": i, "category_id": int(rng.integers(1, classes + 1)),
                         "bbox": list(rng.uniform(0, 100, 2)) + list(rng.uniform(5, 30, 2)),
                         "score": float(rng.uniform(0.05, 1))})
    cats = [{"id": c, "name": f"c{c}"} for c in range(1, classes + 1)]
    return {"images": images, "annotations": anns, "categories": cats}, dets


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weighted_ap_is_pycocotools_on_the_repeated_images(seed):
    gt, dets = random_case(seed)
    m = coco_resample.match(gt, dets)
    ones = np.ones((1, len(gt["images"])))
    assert coco_resample.average_precision(m, ones)[0] == pytest.approx(coco_ap.average_precision(gt, dets)["ap"],
                                                                        abs=1e-12)
    # a bootstrap draw: image 2 twice, image 4 three times, image 1 left out
    counts = np.array([0, 2, 1, 3, 1, 1])
    images, anns, rdets = [], [], []
    for i, k in enumerate(counts, start=1):
        for rep in range(k):
            new = 100 * rep + i
            images.append({"id": new, "width": 200, "height": 100})
            anns += [dict(a, id=len(anns) + 1 + j, image_id=new) for j, a in enumerate(x for x in gt["annotations"]
                                                                                      if x["image_id"] == i)]
            rdets += [dict(d, image_id=new) for d in dets if d["image_id"] == i]
    for j, a in enumerate(anns):
        a["id"] = j + 1
    repeated = {"images": images, "annotations": anns, "categories": gt["categories"]}
    want = coco_ap.average_precision(repeated, rdets)["ap"]
    assert coco_resample.average_precision(m, counts[None].astype(float))[0] == pytest.approx(want, abs=1e-9)
    # many weightings at once equal one at a time
    w = np.random.default_rng(seed).multinomial(6, np.full(6, 1 / 6), size=5).astype(float)
    together = coco_resample.average_precision(m, w, chunk=2)
    alone = [coco_resample.average_precision(m, row[None])[0] for row in w]
    np.testing.assert_allclose(together, alone, equal_nan=True)


# -- BoS and the pre-NMS consistency ------------------------------------------------------------------------------
def test_box_stability_and_cluster_consistency_by_hand():
    from pairedgta.metrics.box_stability import box_stability, cluster_consistency

    a = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float)
    b = np.array([[0, 0, 10, 5], [50, 50, 60, 60], [20, 20, 30, 30]], float)
    # matched: (a0, b0) IoU 0.5, (a1, b2) IoU 1; over min(2, 3) = 2
    assert box_stability(a, np.array([1, 1]), b, np.array([1, 1, 1])) == pytest.approx(0.75)
    assert box_stability(a, np.array([1, 2]), b, np.array([1, 1, 1])) == pytest.approx(0.25)  # classes must agree
    assert box_stability(a, np.array([1, 1]), np.zeros((0, 4)), np.zeros(0, int)) == 0.0
    assert math.isnan(box_stability(np.zeros((0, 4)), np.zeros(0, int), np.zeros((0, 4)), np.zeros(0, int)))
    final = np.array([[0, 0, 10, 10]], float)
    cands = np.array([[0, 0, 10, 10], [0, 0, 10, 5], [0, 0, 10, 8], [40, 40, 50, 50]], float)
    scores = np.array([0.9, 0.3, 0.6, 0.8])
    # IoUs 1, 0.5, 0.8 (>= 0.5) and 0 (another place): (0.9 * 1 + 0.3 * 0.5 + 0.6 * 0.8) / 1.8
    want = (0.9 + 0.15 + 0.48) / 1.8
    assert cluster_consistency(final, np.array([0]), cands, scores, np.zeros(4, int), 0.5) == pytest.approx(want)
    assert math.isnan(cluster_consistency(np.zeros((0, 4)), np.zeros(0, int), cands, scores, np.zeros(4, int), 0.5))


def test_dropout_and_suppression_hooks_on_a_zoo_detector():
    from pairedgta.metrics.box_stability import feature_dropout, image_estimators, no_suppression
    from pairedgta.models import build_model

    det = build_model("tiny_fcos")
    image = np.random.default_rng(0).integers(0, 255, (64, 128, 3), dtype=np.uint8)
    (plain,) = det.detect(image[None])
    with feature_dropout(det, seed=1) as ok:
        assert ok
        (dropped,) = det.detect(image[None])
    (again,) = det.detect(image[None])
    np.testing.assert_array_equal(plain.scores, again.scores)  # the hook is gone
    assert not np.array_equal(plain.scores, dropped.scores)
    thr = det.module.nms_thresh
    with no_suppression(det) as iou:
        assert iou == thr and det.module.nms_thresh == 1.0
    assert det.module.nms_thresh == thr
    out = image_estimators(det, image, plain, 0.0, seed=1)
    assert set(out) == {"bos", "pcr"} and 0.0 <= out["bos"] <= 1.0 and 0.0 < out["pcr"] <= 1.0


# -- the study on a constructed case ------------------------------------------------------------------------------
def constructed(n_models: int = 5, n: int = 6):
    """Every image has 4 objects of class 'car'; detector j finds the first k(j, c) of them (perfect boxes, score
    0.9) and adds one false positive: the better k, the higher both detection xi (the reference found all 4) and AP."""
    from pairedgta.detection.boxes import coco_categories
    from pairedgta.metrics import detection_study as ds

    conditions = ["Day-EXTRASUNNY", "Day-FOGGY", "Night-EXTRASUNNY", "Sunset-RAIN"]
    objects = {i: [(10 + 40 * k, 20, 30, 20) for k in range(4)] for i in range(1, n + 1)}
    images = [{"id": i, "width": 200, "height": 100} for i in objects]
    anns = [{"id": 1 + 4 * (i - 1) + k, "image_id": i, "category_id": 3, "bbox": list(b),
             "area": b[2] * b[3], "iscrowd": 0} for i, boxes in objects.items() for k, b in enumerate(boxes)]
    gt = {"images": images, "annotations": anns, "categories": coco_categories()}
    detectors = []
    for j in range(n_models):
        dets, found, refs, matched, confident = {}, {}, {}, {}, {}
        for ci, c in enumerate(conditions):
            k = max(0, 4 - (j % 4) - (1 if ci == 2 else 0)) if ci else 4
            res = []
            f = np.zeros((n, 8))
            r = np.zeros((n, 8))
            for i, boxes in objects.items():
                for b in boxes[:k]:
                    res.append({"image_id": i, "category_id": 3, "bbox": list(b), "score": 0.9})
                res.append({"image_id": i, "category_id": 3, "bbox": [170, 70, 20, 20], "score": 0.6 - 0.1 * j})
                f[i - 1, 2], r[i - 1, 2] = k, 4
            dets[c], found[c], refs[c] = res, f, r
            matched[c], confident[c] = f[:, 2], f[:, 2] + (0.6 - 0.1 * j >= 0.5)
        detectors.append(ds.Detector(f"m{j}", 0.5, dets, found, refs,
                                     {c: np.arange(8) == 2 for c in conditions}, matched, confident))
    return ds.prepare(detectors, {c: gt for c in conditions}, gt, conditions, conditions[0], n), detectors, gt


def test_the_study_on_a_constructed_case():
    from pairedgta.metrics import detection_study as ds

    study, detectors, gt = constructed()
    v = ds.values(study, np.ones((1, study.n)))
    # the point values are the metrics' own: AP through pycocotools, xi the found share
    for j, d in enumerate(detectors):
        for ci, c in enumerate(study.conditions):
            assert v["ap"][j, 0, ci] == pytest.approx(coco_ap.average_precision(gt, d.detections[c])["ap"], abs=1e-12)
            assert v["det_xi"][j, 0, ci] == pytest.approx(d.found[c][:, 2].sum() / d.refs[c][:, 2].sum())
    cells, stats = ds.compare(study, resamples=50, permutations=100)
    mean = {(r["estimator"], r["target"]): r for r in stats if r["scope"] == "within_mean"}
    # xi and AP order the detectors alike in every adverse condition (ties aside): Spearman 1
    assert mean["det_xi", "ap"]["spearman"] == pytest.approx(1.0)
    assert len(cells) == 5 * 3 and {c["condition"] for c in cells} == set(study.conditions[1:])
    assert not any(r["estimator"] in ds.NEEDS_FORWARDS for r in stats)  # not computed here: not reported
    assert mean["det_xi", "ap"]["n_models"] == 5


def test_the_figure_reads_bos_and_pcr_by_the_written_group_ids(tmp_path):
    """Group ids are written as "00000"; read back as numbers they matched no group and every BoS was NaN."""
    import json

    import pandas as pd

    from pairedgta.detection import registry
    from pairedgta.figures.det_estimators import detector
    from pairedgta.detection.evaluate import DETECTIONS_DIR, SUMMARY, DetectionEvaluateResult

    e = DetectionEvaluateResult("evaluate", "k", tmp_path, False, {"model_config": {"name": "m"}})
    groups, conditions = ["00000", "00001", "00010"], ["Day-EXTRASUNNY", "Night-RAIN"]
    (tmp_path / SUMMARY).write_text(json.dumps({"score_threshold": 0.5}))
    (tmp_path / DETECTIONS_DIR).mkdir()
    for c in conditions:
        (tmp_path / DETECTIONS_DIR / f"{c}.json").write_text("[]")
    rows = [{"group_id": g, "condition": c, "class_name": "car", "found": 1, "reference_boxes": 2, "matched": 1,
             "confident": 1} for g in groups for c in conditions]
    pd.DataFrame(rows).to_csv(tmp_path / registry.GROUP_COUNTS, index=False)
    est = [{"model": "m", "group_id": g, "condition": c, "bos": 0.5 + 0.1 * i, "pcr": 0.9 - 0.1 * i}
           for i, g in enumerate(groups) for c in conditions]
    pd.DataFrame(est).to_csv(tmp_path / registry.ESTIMATORS, index=False)
    d = detector(e, groups[::-1], conditions, min_boxes=1, min_images=1)
    for c in conditions:
        assert d.bos[c] == pytest.approx([0.7, 0.6, 0.5]) and d.pcr[c] == pytest.approx([0.7, 0.8, 0.9])
        assert d.found[c][:, 2].tolist() == [1, 1, 1]


def test_f_of_a_detector_that_finds_nothing_is_zero():
    """xi 0 with no confident box (precision undefined) or with only false ones: F 0, not NaN (0/0)."""
    from pairedgta.metrics import detection_study as ds

    study, _, _ = constructed()
    for key in ("xi_found", "matched"):
        study.sums[key][0] = 0
    study.sums["confident"][0] = 0
    study.sums["confident"][1] = np.where(study.sums["xi_found"][1].sum(-1) > 0, study.sums["confident"][1], 3)
    v = ds.values(study, np.ones((1, study.n)))
    assert np.all(v["det_xi"][0] == 0) and np.all(np.isnan(v["det_precision"][0]))
    assert np.all(v["det_xi_f"][0] == 0)
    assert np.all(np.isfinite(v["det_xi_f"][1:]))
