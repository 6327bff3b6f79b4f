"""A Cityscapes class the model's label space cannot predict (model.labels=ade20k: traffic sign, rider, train) is
reported (terminal, summary.json, MLflow tag) and its xi and IoU are NaN with that reason, never a silent 0; the
means are over the classes the model can predict. A zoo model's entry is as it was (no `reason` column, no keys)."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.evaluation import entry, tables
from pairedgta.evaluation.counting import GT
from pairedgta.report import unpredictable_lines

ADE20K_BLIND = ("traffic sign", "rider", "train")
REASON = "cannot predict (label space ade20k)"
CLEAN, ADVERSE = "Day-EXTRASUNNY", "Night-RAIN"


# -- the tables, from records written by hand --------------------------------------------------------------------
def _settings(convention: str = "strict", absent: str = "nan") -> dict:
    conv = {"name": convention, "absent": absent, "mean_exclude": [], "agreement": "pooled", "rho_headline": "top_m",
            "min_images": 0, "min_pixels": 0}
    return {"clean": CLEAN, "tau_mass": 0.5, "class_ids": list(range(NUM_CLASSES)), "convention": conv,
            "sampling": "all", "min_transmittance": 0.0, "resamples": 50, "confidence": 0.9, "seed": 0,
            "selections": ["top_m"], "m": 25}


def _groups() -> list[dict]:
    """Three groups: road (0) half kept at night, building (2) all kept, traffic sign (7) in the reference but
    never predicted (as a model without a traffic-sign output would): its xi would be a measured-looking 0."""
    road, building, sign = 0, 2, CLASS_NAMES.index("traffic sign")
    groups = []
    for g in range(3):
        reference = np.zeros(NUM_CLASSES, int)
        reference[[road, building, sign]] = [10, 6 + g, 4]
        kept_clean = reference.copy()
        kept_clean[sign] = 0
        kept_night = kept_clean.copy()
        kept_night[road] = 5 - g
        cm = np.zeros((NUM_CLASSES, NUM_CLASSES), int)
        cm[road, road], cm[building, building], cm[sign, building] = 10, 6, 4  # every sign pixel called building
        xi = {f"{source}|{c}": [kept.tolist(), reference.tolist()]
              for source in ("pseudo_label", GT) for c, kept in ((CLEAN, kept_clean), (ADVERSE, kept_night))}
        groups.append({"group_id": f"g{g}", "xi": xi, "cm": {CLEAN: cm.tolist(), ADVERSE: cm.tolist()}})
    return groups


def _write(tmp_path: Path, unpredictable=(), space="", **settings) -> dict:
    covered = {"groups_per_condition": {CLEAN: 3, ADVERSE: 3}, "groups_without_clean": 0}
    e = entry.ModelEvaluation("d", "m", "ref", [CLEAN, ADVERSE], _settings(**settings), _groups(), covered,
                              unpredictable=tuple(unpredictable), label_space=space)
    return entry.write_outputs(tmp_path, e, [tables.Xi(), tables.GtIoU()])  # the two tables of the classes


@pytest.mark.parametrize("absent", ["nan", "zero"])
def test_unpredictable_classes_are_nan_with_the_reason_and_left_out_of_the_means(tmp_path, absent):
    summary = _write(tmp_path, ADE20K_BLIND, "ade20k", absent=absent)
    xi = pd.read_csv(tmp_path / tables.XI, keep_default_na=False, na_values=[""])
    for (source, cond), part in xi.groupby(["reference_model", "condition"]):
        rows = part.set_index("class_name")
        for name in ADE20K_BLIND:  # NaN, no interval, out of the mean, with the reason
            row = rows.loc[name]
            assert math.isnan(row.xi) and math.isnan(row.ci_low) and math.isnan(row.ci_high)
            assert not row.in_mean and row.classes == 0 and row.reason == REASON
        sign = rows.loc["traffic sign"]
        assert sign.reference_pixels == 12 and sign.retained_pixels == 0  # the counts stay: only xi is undefined
        others = rows.drop(index=[*ADE20K_BLIND, "mean"])
        assert others["reason"].isna().all() and pd.isna(rows.loc["mean", "reason"])
        included = others[others["in_mean"]]
        expected = included["xi"].mean()  # by hand: road and building (the absent ones as 0 under `zero`)
        assert rows.loc["mean", "xi"] == pytest.approx(expected)
        assert rows.loc["mean", "classes"] == len(included) == (2 if absent == "nan" else NUM_CLASSES - 3)
        if cond == ADVERSE:  # a real interval over the predictable classes (road varies), not zero width
            assert rows.loc["mean", "ci_low"] < rows.loc["mean", "ci_high"]
        key = "xi_mean" if source == "ref" else "xi_mean_gt"
        assert summary[key][cond] == pytest.approx(expected)
    iou = pd.read_csv(tmp_path / tables.GT_IOU, keep_default_na=False, na_values=[""])
    for cond, part in iou.groupby("condition"):
        rows = part.set_index("class_name")
        assert all(math.isnan(rows.loc[n, "iou"]) and rows.loc[n, "reason"] == REASON for n in ADE20K_BLIND)
        # road 1; building 18 / (18 + 12 called building) = 0.6; the sign's 0 is not a measured 0
        assert rows.loc["mean", "iou"] == pytest.approx((1.0 + 0.6) / 2) == summary["gt_miou"][cond]
        assert pd.isna(rows.loc["mean", "reason"])
    written = json.loads((tmp_path / entry.SUMMARY).read_text())
    assert written["label_space"] == "ade20k" and written["unpredictable_classes"] == list(ADE20K_BLIND)


def test_estimators_csv_xi_is_the_same_mean(tmp_path):
    """estimators.csv's xi (from group_counts.npz) leaves the same classes out as xi.csv's mean."""
    summary = _write(tmp_path, ADE20K_BLIND, "ade20k")
    ms = [tables.Xi(), tables.GtIoU(), tables.Estimators()]
    arrays = entry.write_group_counts(tmp_path / "counts.npz", _groups(), [CLEAN, ADVERSE], ms)
    blind = np.array([n in ADE20K_BLIND for n in CLASS_NAMES])
    with np.errstate(all="ignore"):
        values = tables.write_estimators(tmp_path, "m", [CLEAN, ADVERSE], _settings(), arrays, blind)
    # road kept 12 of 30 at night, building all: (0.4 + 1) / 2, not (0.4 + 1 + 0) / 3 with the sign's 0
    assert values[ADVERSE]["xi"] == pytest.approx(0.7) == summary["xi_mean"][ADVERSE]


def test_a_model_that_predicts_every_class_writes_what_it_always_did(tmp_path):
    """No `reason` column, no summary keys, the traffic sign's measured 0 in xi and IoU: the entry of a zoo
    model (or a source model whose label space reaches all 19 classes) is byte for byte as before."""
    summary = _write(tmp_path)
    xi, iou = pd.read_csv(tmp_path / tables.XI), pd.read_csv(tmp_path / tables.GT_IOU)
    assert "reason" not in xi and "reason" not in iou
    assert "label_space" not in summary and "unpredictable_classes" not in summary
    sign = xi[(xi["class_name"] == "traffic sign")]
    assert (sign["xi"] == 0).all() and sign["in_mean"].all()
    assert (iou[iou["class_name"] == "traffic sign"]["iou"] == 0).all()
    assert unpredictable_lines({"m": str(tmp_path)}) == []


def test_the_report_line_and_the_label_space_of_a_config(tmp_path):
    from pairedgta.evaluation.work import label_tags

    folder = tmp_path / "e"
    folder.mkdir()
    (folder / entry.SUMMARY).write_text(json.dumps({"model": "net", "label_space": "coco_panoptic",
                                                    "unpredictable_classes": ["pole", "rider"]}))
    assert unpredictable_lines({"net": str(folder), "gone": str(tmp_path / "missing")}) == [
        "net: cannot predict pole, rider (label space coco_panoptic): their xi and IoU are NaN"]
    source = {"name": "net", "family": "python", "target": "x:y", "labels": "ade20k"}
    assert entry.label_space(source) == ("ade20k", ADE20K_BLIND)
    assert label_tags(source) == {"unpredictable_classes": "traffic sign,rider,train", "label_space": "ade20k"}
    assert entry.label_space({**source, "labels": "cityscapes"}) == ("cityscapes", ())
    assert label_tags({**source, "labels": "cityscapes"}) == {}
    zoo = {"name": "tiny_segformer", "family": "segformer"}
    assert entry.label_space(zoo) == ("", ()) and label_tags(zoo) == {}


# -- the real CLI ----------------------------------------------------------------------------------------------
NET = """import torch


def build():
    return torch.nn.Conv2d(3, 150, 1)  # 150 logits: ADE20K's classes
"""


def _entries(stdout: str) -> dict[str, Path]:
    return {m.group(1): Path(m.group(2)) for m in re.finditer(r"^  evaluate \[(.+?)\]: (.+)$", stdout, re.M)}


@pytest.mark.slow
def test_an_ade20k_model_through_the_cli(tmp_path, monkeypatch):
    import torch

    from pairedgta.testing.cli import fast_overrides, run_cli

    (tmp_path / "mynet_ade.py").write_text(NET)
    monkeypatch.syspath_prepend(str(tmp_path))
    torch.manual_seed(0)
    weights = tmp_path / "mynet.pt"
    torch.save(torch.nn.Conv2d(3, 150, 1).state_dict(), weights)
    # every class with reference pixels enters the means (no support rule): the sign's 0 would count
    common = fast_overrides(tmp_path) + ["reference_model=tiny_segformer", "metric.min_images=0", "metric.min_pixels=0"]
    r = run_cli(common + ["model=python", "model.name=mynet", "model.target=mynet_ade:build", "model.labels=ade20k",
                          f"model.checkpoint_path={weights}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "  mynet: cannot predict traffic sign, rider, train (label space ade20k): their xi and IoU are NaN" \
        in r.stdout.splitlines()
    out = _entries(r.stdout)["mynet"]
    summary = json.loads((out / entry.SUMMARY).read_text())
    assert summary["label_space"] == "ade20k" and summary["unpredictable_classes"] == list(ADE20K_BLIND)

    xi = pd.read_csv(out / tables.XI, keep_default_na=False, na_values=[""])
    assert set(xi.loc[xi["reason"].notna(), "class_name"]) == set(ADE20K_BLIND)
    blind = xi[xi["class_name"].isin(ADE20K_BLIND)]
    assert blind[["xi", "ci_low", "ci_high"]].isna().all().all() and (blind["reason"] == REASON).all()
    assert not blind["in_mean"].any()
    # the synthetic street shows traffic signs: without the reason they would have been a measured 0
    assert blind.loc[blind["class_name"] == "traffic sign", "reference_pixels"].sum() > 0
    for (source, cond), part in xi.groupby(["reference_model", "condition"]):
        rows = part[part["class_name"] != "mean"]
        mean = part[part["class_name"] == "mean"].iloc[0]
        # by hand from the CSV: every class with reference pixels (strict: absent ones undefined), those it
        # cannot predict left out
        by_hand = rows[(rows["reference_pixels"] > 0) & ~rows["class_name"].isin(ADE20K_BLIND)]["xi"].mean()
        assert mean["xi"] == pytest.approx(by_hand)
        assert summary["xi_mean" if source != GT else "xi_mean_gt"][cond] == pytest.approx(by_hand)
    iou = pd.read_csv(out / tables.GT_IOU, keep_default_na=False, na_values=[""])
    for cond, part in iou.groupby("condition"):
        rows = part[part["class_name"] != "mean"]
        blind = rows[rows["class_name"].isin(ADE20K_BLIND)]
        assert blind["iou"].isna().all() and (blind["reason"] == REASON).all()
        assert rows[~rows["class_name"].isin(ADE20K_BLIND)]["reason"].isna().all()
        by_hand = rows[~rows["class_name"].isin(ADE20K_BLIND)]["iou"].mean()  # pandas skips the undefined
        assert part[part["class_name"] == "mean"]["iou"].iloc[0] == pytest.approx(by_hand)
        assert summary["gt_miou"][cond] == pytest.approx(by_hand)

    # a zoo model on the same scenes and pseudo-labels: no reason, no keys, no line
    r = run_cli(common + ["model=tiny_segformer"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "cannot predict" not in r.stdout
    out = _entries(r.stdout)["tiny_segformer"]
    summary = json.loads((out / entry.SUMMARY).read_text())
    assert "label_space" not in summary and "unpredictable_classes" not in summary
    assert "reason" not in pd.read_csv(out / tables.XI) and "reason" not in pd.read_csv(out / tables.GT_IOU)


@pytest.mark.slow
def test_the_mlflow_run_of_the_model_is_tagged(tmp_path, monkeypatch):
    import torch
    from mlflow.tracking import MlflowClient

    from pairedgta.testing.cli import base_overrides, fast_overrides, run_cli

    (tmp_path / "mynet_tag.py").write_text(NET.replace("150", "133").replace("ADE20K", "COCO panoptic"))
    monkeypatch.syspath_prepend(str(tmp_path))
    weights = tmp_path / "mynet.pt"
    torch.save(torch.nn.Conv2d(3, 133, 1).state_dict(), weights)
    uri = base_overrides(tmp_path)[1]
    args = [a for a in fast_overrides(tmp_path) if not a.startswith(("tracking.", "plot."))]
    r = run_cli(args + [uri, "tracking.enabled=true", "stages=[generate,pseudolabel,evaluate]",
                        "model=python", "model.name=panoptic", "model.target=mynet_tag:build",
                        "model.labels=coco_panoptic", f"model.checkpoint_path={weights}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    client = MlflowClient(tracking_uri=uri.split("=", 1)[1])
    runs = [run for exp in client.search_experiments() for run in client.search_runs([exp.experiment_id])]
    tagged, = [run for run in runs if run.data.tags.get("model") == "panoptic"]
    assert tagged.data.tags["unpredictable_classes"] == "pole,rider"
    assert tagged.data.tags["label_space"] == "coco_panoptic"
