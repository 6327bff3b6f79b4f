"""task=detection: ground truth from instance masks, detection xi against a hand count, COCO AP against the library,
the precision side, P / mPC / rPC, bad input, and the task run through the CLI on the synthetic backend."""
from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.detection.boxes import INSTANCE_CLASSES, boxes_from_instances, coco_ground_truth, read_box_file
from pairedgta.metrics import coco_ap, corruption, detection_xi

CAR, PERSON, SIGN = CLASS_NAMES.index("car"), CLASS_NAMES.index("person"), CLASS_NAMES.index("traffic sign")
CAR_I, PERSON_I = INSTANCE_CLASSES.index("car"), INSTANCE_CLASSES.index("person")


def scene() -> tuple[np.ndarray, np.ndarray]:
    """40 x 60: a car (id 1) partly hidden by a person (id 2), a car cut by the right border (id 3), a 3x3 person
    (id 4, under the minimum area), a sign with an instance id (id 5, not a detection class)."""
    inst = np.zeros((40, 60), np.uint16)
    lab = np.zeros((40, 60), np.uint8)
    inst[10:30, 5:25], lab[10:30, 5:25] = 1, CAR
    inst[5:35, 20:28], lab[5:35, 20:28] = 2, PERSON  # in front of the car: the car's visible box ends at x=20
    inst[0:12, 50:60], lab[0:12, 50:60] = 3, CAR
    inst[36:39, 2:5], lab[36:39, 2:5] = 4, PERSON
    inst[2:6, 30:34], lab[2:6, 30:34] = 5, SIGN
    return inst, lab


def test_boxes_are_the_tight_visible_extent_with_the_rules():
    inst, lab = scene()
    boxes = {b.instance: b for b in boxes_from_instances(inst, lab, min_area=20)}
    assert set(boxes) == {1, 2, 3, 4}  # the sign is not a detection class
    assert boxes[1].xyxy == (5.0, 10.0, 20.0, 30.0) and boxes[1].area == 15 * 20 and boxes[1].label == CAR_I
    assert boxes[2].xyxy == (20.0, 5.0, 28.0, 35.0) and boxes[2].label == PERSON_I and not boxes[2].truncated
    assert boxes[3].truncated and boxes[3].xyxy == (50.0, 0.0, 60.0, 12.0) and not boxes[3].ignore
    assert boxes[4].ignore == "small" and boxes[4].area == 9
    assert all(not boxes[k].ignore for k in (1, 2, 3))


def test_fog_rule_makes_an_object_mostly_unseen_an_ignore_region():
    inst, lab = scene()
    t = np.ones(inst.shape, np.float32)
    t[10:30, 5:16] = 0.01  # 11 of the car's 15 visible columns under the threshold
    t[5:35, 20:22] = 0.01  # 2 of the person's 8 columns
    boxes = {b.instance: b for b in boxes_from_instances(inst, lab, min_area=20, transmittance=t, min_transmittance=0.05)}
    assert boxes[1].ignore == "fog" and boxes[2].ignore == "" and boxes[2].transmittance == pytest.approx(0.7525)
    plain = {b.instance: b for b in boxes_from_instances(inst, lab, min_area=20, transmittance=t)}
    assert plain[1].ignore == ""  # min_transmittance 0: the rule is off


def test_box_file_of_a_renderer_without_masks(tmp_path):
    path = tmp_path / "Day-RAIN_boxes.json"
    path.write_text(json.dumps({"boxes": [{"class": "car", "bbox": [1, 2, 31, 22], "instance": 7},
                                          {"class": "person", "bbox": [0, 0, 5, 5]}, {"class": "Misc", "bbox": [0, 0, 9, 9]}]}))
    boxes = read_box_file(path, min_area=100)
    assert [(b.instance, INSTANCE_CLASSES[b.label], b.ignore) for b in boxes] == [(7, "car", ""), (2, "person", "small")]
    path.write_text("{not json")
    from pairedgta.errors import DataError
    with pytest.raises(DataError, match="Day-RAIN_boxes.json: not a boxes file"):
        read_box_file(path)


def test_detection_xi_counts_match_a_hand_count():
    ref = np.array([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10]], float)
    ref_labels = np.array([CAR_I, CAR_I, PERSON_I])
    boxes = np.array([[0, 0, 10, 11],    # car, IoU 0.91 with ref 0: found
                      [1, 0, 11, 10],    # car, also on ref 0 (lower score): ref 0 is taken, no second match
                      [20, 0, 30, 10],   # person on the car ref 1: wrong class, not found
                      [40, 0, 50, 10],   # person on ref 2 but under the threshold
                      [60, 0, 70, 10]],  # car on nothing
                     float)
    scores = np.array([0.9, 0.8, 0.95, 0.3, 0.7])
    labels = np.array([CAR_I, CAR_I, PERSON_I, PERSON_I, CAR_I])
    c = detection_xi.image_counts(ref, ref_labels, boxes, scores, labels, threshold=0.5, iou=0.5, num_classes=8)
    # reference boxes, found, confident boxes, confident boxes matched
    assert c[:, CAR_I].tolist() == [2, 1, 3, 1]
    assert c[:, PERSON_I].tolist() == [1, 0, 1, 0]
    assert c.sum(axis=1).tolist() == [3, 1, 4, 1]


def _coco_case():
    images = [(1, "a.png", 100, 100), (2, "b.png", 100, 100)]
    gt = coco_ground_truth(images, [
        boxes_from_instances(*_two_cars()), []])
    dets = [{"image_id": 1, "category_id": CAR_I + 1, "bbox": [10, 10, 20, 20], "score": 0.9},
            {"image_id": 1, "category_id": CAR_I + 1, "bbox": [52, 50, 20, 20], "score": 0.8},
            {"image_id": 2, "category_id": CAR_I + 1, "bbox": [0, 0, 10, 10], "score": 0.95}]
    return gt, dets


def _two_cars():
    inst = np.zeros((100, 100), np.uint16)
    lab = np.zeros((100, 100), np.uint8)
    inst[10:30, 10:30], lab[10:30, 10:30] = 1, CAR
    inst[50:70, 50:70], lab[50:70, 50:70] = 2, CAR
    return inst, lab


def test_coco_ap_is_the_librarys_on_a_fixed_case():
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt, dets = _coco_case()
    ours = coco_ap.average_precision(gt, dets)
    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = json.loads(json.dumps(gt))
        g.createIndex()
        ev = COCOeval(g, g.loadRes(json.loads(json.dumps(dets))), "bbox")
        ev.evaluate(), ev.accumulate(), ev.summarize()
    assert ours["ap"] == pytest.approx(ev.stats[0]) and ours["ap50"] == pytest.approx(ev.stats[1])
    assert ours["ap75"] == pytest.approx(ev.stats[2])
    # by hand: the false positive on image 2 scores highest, then the two cars (IoU 1 and 0.82 at .5): precision
    # 1/2 at recall 1/2 and 2/3 at recall 1: AP50 = interpolated 2/3 over the 101 recall points
    assert ours["ap50"] == pytest.approx(2 / 3, abs=1e-9)
    assert math.isnan(ours["per_class"][PERSON_I + 1][0])  # no person in the ground truth: NaN, not 0


def test_an_image_set_without_objects_is_nan_with_its_reason():
    gt = coco_ground_truth([(1, "a.png", 10, 10)], [[]])
    r = coco_ap.average_precision(gt, [{"image_id": 1, "category_id": 1, "bbox": [0, 0, 5, 5], "score": 0.9}])
    assert math.isnan(r["ap"]) and "no scored object" in r["reason"]


def test_corruption_scores_as_michaelis():
    perf = {"clean": 0.4, "a": 0.2, "b": 0.1}
    s = corruption.corruption_scores(perf, "clean", ["a", "b"])
    assert s == pytest.approx({"P": 0.4, "mPC": 0.15, "rPC": 0.375})
    assert math.isnan(corruption.corruption_scores({"clean": 0.0, "a": 0.0}, "clean", ["a"])["rPC"])
    assert math.isnan(corruption.corruption_scores({"clean": 0.001, "a": 0.001}, "clean", ["a"])["rPC"])  # no P
    subsets = corruption.subsets(["Day-RAIN", "Night-CLEAR", "Night-RAIN"], "Day-CLEAR")
    assert subsets["Night-*"] == ["Night-CLEAR", "Night-RAIN"] and subsets["*-RAIN"] == ["Day-RAIN", "Night-RAIN"]


def test_a_detector_firing_everywhere_keeps_every_box_but_is_scored_low():
    """xi is a recall: boxes everywhere find every reference box. The precision side and pseudo-AP show it."""
    from pairedgta.detection import registry
    from pairedgta.detection.inputs import GroupResult, Inputs
    from pairedgta.models.detectors import Detections

    rng = np.random.default_rng(0)
    groups, pseudo, honest_groups = [], {}, []
    grid = np.array([[x, y, x + w, y + w] for w in (8, 16, 24) for x in range(0, 120, 3) for y in range(0, 60, 3)],
                    np.float32)
    for g in range(6):
        ref = np.array([[10 + g, 10, 30 + g, 30], [60, 20, 76, 44]], np.float32)
        labels = np.array([CAR_I, PERSON_I])
        pseudo[f"{g}"] = Detections(ref, np.array([0.9, 0.8], np.float32), labels)
        spam = Detections(np.concatenate([grid, grid]), np.full(2 * len(grid), 0.99, np.float32),
                          np.repeat([CAR_I, PERSON_I], len(grid)))
        honest = Detections(ref + rng.normal(0, 0.5, ref.shape).astype(np.float32), np.array([0.9, 0.6], np.float32),
                            labels)
        for store, d in ((groups, spam), (honest_groups, honest)):
            counts = {c: detection_xi.image_counts(ref, labels, d.boxes, d.scores, d.labels, 0.5, 0.5, 8)
                      for c in ("clean", "fog")}
            store.append(GroupResult(f"{g}", {"clean": d, "fog": d}, counts, [], {"clean": (64, 128), "fog": (64, 128)}))
    settings = {"min_boxes": 5, "min_images": 3, "max_detections": 100000, "bootstrap": {"resamples": 100,
                "confidence": 0.95, "seed": 0}}
    ids = {f"{g}": g + 1 for g in range(6)}
    scores = {}
    for name, gs in (("spam", groups), ("honest", honest_groups)):
        inputs = Inputs(name, "ref", ["clean", "fog"], "clean", gs, ids, pseudo, {}, 0.5, settings)
        tables, values = registry.xi_tables(inputs)
        scores[name] = values
        xi = tables[registry.XI]
        assert xi.loc[(xi.class_name == "rider"), "xi"].isna().all()  # no reference riders: NaN, never 0
    assert scores["spam"]["xi_mean"]["fog"] == 1.0 and scores["honest"]["xi_mean"]["fog"] == 1.0
    assert scores["spam"]["precision"]["fog"] < 0.01 and scores["honest"]["precision"]["fog"] == 1.0
    assert scores["spam"]["pseudo_ap50"]["fog"] < 0.5 * scores["honest"]["pseudo_ap50"]["fog"]


def test_a_model_of_the_other_task_is_one_line_before_any_stage(tmp_path):
    from pairedgta.testing.cli import fast_overrides, run_cli

    proc = run_cli(fast_overrides(tmp_path) + ["task=detection"], tmp_path)
    assert proc.returncode != 0
    err = (proc.stdout + proc.stderr).strip().splitlines()
    assert any("model=tiny_segformer is a segmenter (label maps), but task=detection needs a detector" in l for l in err)
    assert not any((tmp_path / "cache").rglob("*"))  # nothing written
    proc = run_cli(fast_overrides(tmp_path) + ["model=tiny_fcos", "reference_model=tiny_fcos"], tmp_path)
    assert proc.returncode != 0 and "is a detector (boxes), but task=segmentation needs a segmenter" in proc.stderr + proc.stdout
    proc = run_cli(fast_overrides(tmp_path) + ["task=detection", "model=tiny_fcos", "reference_model=tiny_fcos",
                                               "plot.figures=[xi_models]"], tmp_path)
    assert proc.returncode != 0 and "plot.figures=['xi_models'] draw(s) another task's results" in proc.stderr + proc.stdout


def detection_overrides(tmp_path) -> list[str]:
    from pairedgta.testing.cli import base_overrides

    return base_overrides(tmp_path, store=False) + [
        "+experiment=smoke_detection", "renderer.width=96", "renderer.height=48", "generate.num_scenes=3",
        "conditions.only=[Day-EXTRASUNNY,Day-FOGGY,Night-EXTRASUNNY]", "models=[tiny_fcos,tiny_fasterrcnn]",
        "metric.bootstrap.resamples=50", "plot.formats=[png]", "plot.dpi=50", "tracking.enabled=false", "threads=1"]


def entries(stage_dir):
    return sorted(p for p in stage_dir.iterdir() if p.is_dir() and not p.name.startswith("."))


@pytest.mark.slow
def test_task_detection_through_the_cli(tmp_path):
    from pairedgta.testing.cli import run_cli

    proc = run_cli(detection_overrides(tmp_path), tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "mean detection xi" in out and "tiny_fasterrcnn (reference)" in out
    cache = tmp_path / "cache"
    (labels,) = entries(cache / "pseudolabel")
    gt = json.loads((labels / "ground_truth" / "Day-FOGGY.json").read_text())
    assert gt["categories"][2]["name"] == "car" and gt["images"] and gt["annotations"]
    evaluations = entries(cache / "evaluate")
    assert len(evaluations) == 2
    for e in evaluations:
        summary = json.loads((e / "summary.json").read_text())
        assert summary["task"] == "detection" and set(summary["xi_mean"]) == {"Day-EXTRASUNNY", "Day-FOGGY",
                                                                              "Night-EXTRASUNNY"}
        dets = json.loads((e / "detections" / "Night-EXTRASUNNY.json").read_text())
        assert all(set(d) == {"image_id", "category_id", "bbox", "score"} for d in dets)
        for f in ("detection_xi.csv", "detection_ap.csv", "detection_robustness.csv", "detection_objects.csv",
                  "detection_objects_found.csv"):
            assert (e / f).is_file(), f
    plots = list((cache / "plot").glob("*/det_xi_models.png"))
    assert plots and list((cache / "plot").glob("*/det_robustness.png")) and list((cache / "plot").glob("*/det_objects.png"))
    again = run_cli(detection_overrides(tmp_path), tmp_path)
    assert again.returncode == 0 and again.stdout.count("cache hit") + again.stderr.count("cache hit") >= 4


@pytest.mark.slow
def test_detection_shards_merge_to_the_unsharded_result(tmp_path):
    from pairedgta.testing.cli import run_cli

    base = detection_overrides(tmp_path) + ["models=[tiny_fcos]", "plot.figures=[det_xi]"]
    logs = []
    for shard in (0, 1):
        proc = run_cli(base + ["evaluate.num_shards=2", f"evaluate.shard={shard}", "stages=[generate,pseudolabel,evaluate]"],
                       tmp_path)
        assert proc.returncode == 0, (proc.stdout + proc.stderr)[-2000:]
        logs.append(proc.stdout + proc.stderr)
    assert "1 of 3 groups evaluated by shards so far" not in logs[0] and "2 of 3 groups" in logs[0]
    assert "merging 3 group(s) from shard jobs, computing 0" in logs[1]  # the last shard completes the entry
    merged = run_cli(base + ["stages=[evaluate]"], tmp_path)
    assert merged.returncode == 0 and "cache hit" in merged.stdout + merged.stderr
    (entry,) = entries(tmp_path / "cache" / "evaluate")
    sharded = (entry / "detection_xi.csv").read_text()
    fresh = run_cli(base + ["stages=[evaluate]", "force=[evaluate]"], tmp_path)
    assert fresh.returncode == 0
    assert (entry / "detection_xi.csv").read_text() == sharded


@pytest.mark.slow
def test_a_dataset_without_instance_masks_skips_gt_with_one_line_and_keeps_xi(tmp_path):
    """The released PairedGTA layout has images only: GT metrics are skipped with one warning, xi is computed."""
    import sys
    from pathlib import Path

    from pairedgta.testing.cli import base_overrides, run_cli

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    from bench_evaluate import make_release_dataset

    root = tmp_path / "release"
    make_release_dataset(root, 3, 96, 48)
    proc = run_cli(base_overrides(tmp_path, store=False) + [
        "task=detection", "dataset=paired_gta", f"dataset.root={root}", "model=tiny_fcos", "models=[tiny_fcos]",
        "reference_model=tiny_fasterrcnn", "+model_overrides.tiny_fasterrcnn.score_threshold=0.05",
        "pseudolabel.tau=0.05", "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]",
        "stages=[pseudolabel,evaluate]", "tracking.enabled=false", "metric.bootstrap.resamples=20", "threads=1"],
        tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    warnings = [line for line in out.splitlines() if "no instance masks or boxes" in line]
    assert len(warnings) == 1 and "ground-truth AP is skipped, detection xi is still computed" in warnings[0]
    (entry,) = entries(tmp_path / "cache" / "evaluate")
    assert (entry / "detection_xi.csv").is_file() and not (entry / "detection_ap.csv").exists()
    summary = json.loads((entry / "summary.json").read_text())
    assert "none" in summary["ground_truth"] and "gt_ap" not in summary


def test_the_cityscapes_check_runs_the_tasks_models():
    from omegaconf import OmegaConf

    from pairedgta.testing.cli import compose_cfg

    for task, first in (("segmentation", "segformer_b5"), ("detection", "demo_fcos_adverse")):
        cfg = OmegaConf.to_container(compose_cfg(["+experiment=cityscapes_val_check", f"task={task}"]), resolve=True)
        assert cfg["models"][0] == first


@pytest.mark.slow
def test_cityscapes_box_ap_check_through_the_cli(tmp_path):
    """+experiment=cityscapes_val_check task=detection: box AP against gtFine's instance ids, as pycocotools gives it
    for the same detections."""
    from PIL import Image

    from pairedgta.detection.real_boxes import read_cityscapes_boxes
    from pairedgta.models import build_model
    from pairedgta.testing.cli import run_cli

    rng = np.random.default_rng(0)
    img_dir, gt_dir = tmp_path / "cs" / "leftImg8bit" / "val" / "ulm", tmp_path / "cs" / "gtFine" / "val" / "ulm"
    img_dir.mkdir(parents=True), gt_dir.mkdir(parents=True)
    detector = build_model("tiny_fcos")
    images, gts, results = [], [], []
    for k in range(2):
        fid = f"ulm_000000_00000{k}"
        image = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
        ids = np.full((64, 128), 7, np.uint16)
        ids[10:40, 20:60] = 26001 + k
        ids[30:60, 80:95] = 24001
        Image.fromarray(image).save(img_dir / f"{fid}_leftImg8bit.png")
        Image.fromarray(np.zeros((64, 128), np.uint8)).save(gt_dir / f"{fid}_gtFine_labelTrainIds.png")
        Image.fromarray(ids).save(gt_dir / f"{fid}_gtFine_instanceIds.png")
        d = detector.detect(image[None])[0]
        images.append((k + 1, fid, 128, 64))
        gts.append(read_cityscapes_boxes(gt_dir / f"{fid}_gtFine_instanceIds.png"))
        results += coco_ap.results_format(k + 1, d.boxes, d.scores, d.labels + 1)
    expected = coco_ap.average_precision(coco_ground_truth(images, gts), results)
    proc = run_cli(["+experiment=cityscapes_val_check", "task=detection", f"dataset.root={tmp_path / 'cs'}",
                    "models=[tiny_fcos]", "reference_model=tiny_fcos", f"cache_dir={tmp_path / 'cache'}",
                    "tracking.enabled=false"], tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    (entry,) = entries(tmp_path / "cache" / "cityscapes_val")
    summary = json.loads((entry / "summary.json").read_text())
    assert summary["task"] == "detection" and summary["objects"] == 4
    assert summary["ap"] == pytest.approx(expected["ap"], nan_ok=True)
    assert summary["ap50"] == pytest.approx(expected["ap50"], nan_ok=True)
    assert "box AP" in out


@pytest.mark.slow
def test_a_sweep_over_detectors_then_plot_collects_them(tmp_path):
    from pairedgta.testing.cli import run_cli

    base = [o for o in detection_overrides(tmp_path) if not o.startswith("models=")]
    proc = run_cli(base + ["model=tiny_fcos,tiny_retinanet", "stages=[generate,pseudolabel,evaluate]"], tmp_path,
                   multirun=True)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert len(entries(tmp_path / "cache" / "evaluate")) == 2
    plot = run_cli(base + ["model=tiny_fcos", "plot.collect_cached=true", "stages=[plot]",
                           "plot.figures=[det_xi]"], tmp_path)
    out = plot.stdout + plot.stderr
    assert plot.returncode == 0 and "collected 1 cached evaluation(s) of this dataset: tiny_retinanet" in out
    (figure,) = list((tmp_path / "cache" / "plot").glob("*/det_xi_models.csv"))
    import pandas as pd
    assert set(pd.read_csv(figure)["model"]) == {"tiny_fcos", "tiny_retinanet"}


def test_a_checkpoint_of_other_classes_is_one_line(tmp_path):
    from safetensors.torch import save_file

    from pairedgta.models.detectors import fcos
    from pairedgta.errors import ModelError
    from pairedgta.models import build_model, model_config

    cfg = model_config("tiny_fcos")
    coco = fcos("coco", 91, 128, 256, width=cfg["width"], fpn_channels=cfg["fpn_channels"])
    path = tmp_path / "coco_fcos.safetensors"
    save_file({k: v.contiguous() for k, v in coco.state_dict().items()}, str(path))
    with pytest.raises(ModelError) as err:
        build_model({**cfg, "random_init": False, "checkpoint_path": str(path)})
    message = str(err.value)
    assert "\n" not in message and "predicts 91 classes" in message and "background + person, rider, car" in message

