"""The label-free estimators' raw material, written by evaluate from the same forward pass as xi."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pairedgta.models.base import normalised_entropy
from pairedgta.evaluation import counting, entry, registry, shards, tables


def test_normalised_entropy_is_zero_when_certain_one_when_uniform_and_renormalises():
    k = 19
    probs = torch.zeros(1, k, 1, 3)
    probs[0, 4, 0, 0] = 1.0                       # certain
    probs[0, :, 0, 1] = 1.0 / k                   # uniform
    probs[0, :2, 0, 2] = torch.tensor([0.3, 0.3])  # scores summing to 0.6 (Mask2Former-like): two classes, 50/50
    h = normalised_entropy(probs)[0, 0]
    assert h[0] == pytest.approx(0.0, abs=1e-6) and h[1] == pytest.approx(1.0, abs=1e-5)
    assert h[2] == pytest.approx(math.log(2) / math.log(k), abs=1e-6)


def test_estimator_sums_of_one_image_by_hand():
    pred = np.array([[1, 2], [3, 4]])
    clean = np.array([[1, 2], [0, 0]])           # two of four pixels predicted as on the clean image
    conf = np.array([[0.25, 0.5], [0.9995, 1.0]], dtype=np.float32)
    entropy = np.array([[0.5, 0.25, 0.0, 0.0]], dtype=np.float32).reshape(2, 2)
    s = counting.estimator_sums(pred, conf, entropy, clean)
    assert s["pixels"] == 4 and s["agree_clean"] == 2
    assert s["conf_sum"] == pytest.approx(2.7495, abs=1e-6) and s["entropy_sum"] == pytest.approx(0.75)
    hist = np.asarray(s["conf_hist"])
    assert hist.shape == (counting.CONF_BINS,) and hist.sum() == 4
    # bin k holds [k/1000, (k+1)/1000); 1.0 falls into the last bin with 0.9995
    assert hist[250] == 1 and hist[500] == 1 and hist[999] == 2


class _Fixed:
    """A segmenter whose probabilities are given: the first half of each image certain of class 0 at
    probability 0.875 (the rest spread evenly), the second half class 1 at 0.625 on the dark image (binary-exact
    probabilities, so the histogram bins are known)."""

    name = "fixed"

    def predict_with_entropy(self, images):
        b, h, w, _ = images.shape
        probs = torch.full((b, 19, h, w), 0.125 / 18)
        probs[:, 0, :, : w // 2] = 0.875
        for i in range(b):
            cls, p = (0, 0.875) if images[i].mean() > 100 else (1, 0.625)  # bright = clean image
            probs[i, :, :, w // 2 :] = (1 - p) / 18
            probs[i, cls, :, w // 2 :] = p
        conf, labels = probs.max(1)
        return labels, conf, normalised_entropy(probs)


def test_group_counts_carry_estimator_sums_and_label_maps_from_the_same_pass():
    clean, adverse = "Day-EXTRASUNNY", "Night-RAIN"
    images = {clean: np.full((4, 6, 3), 200, np.uint8), adverse: np.full((4, 6, 3), 20, np.uint8)}
    pseudo = np.zeros((4, 6), np.uint8)
    item = {"group_id": "g0", "present": [clean, adverse], "images": images, "pseudo": pseudo, "own": {}}
    s = {"clean": clean, "tau_mass": 0.5, "class_ids": [0, 1]}
    out = counting.group_counts(item, _Fixed(), s, clean, True, 2, "fixed", "d")
    e = out["estimators"][adverse]
    assert e["pixels"] == 24 and e["agree_clean"] == 12  # the right half turns from class 0 to class 1
    assert e["conf_sum"] == pytest.approx(12 * 0.875 + 12 * 0.625, rel=1e-5)
    assert np.asarray(e["conf_hist"])[[625, 875]].tolist() == [12, 12]
    assert out["estimators"][clean]["agree_clean"] == 24
    assert out["pred"][adverse].dtype == np.uint8 and (out["pred"][adverse][:, 3:] == 1).all()


def test_estimator_arrays_predictions_and_shard_parts_round_trip(tmp_path):
    conds = ["Day-EXTRASUNNY", "Day-RAIN"]
    hist = [0] * counting.CONF_BINS
    hist[10] = 6
    results = [{"group_id": f"s{g}", "xi": {}, "cm": {}, "agreement": [], "counts": [],
                "estimators": {c: {"pixels": 6, "conf_sum": 1.5 + g, "entropy_sum": 0.5, "conf_hist": hist,
                                   "agree_clean": 3} for c in conds[: 2 - g]},
                "pred": {c: np.full((2, 3), g + i, np.uint8) for i, c in enumerate(conds[: 2 - g])}} for g in range(2)]
    entry.write_group_counts(tmp_path / "gc.npz", results, conds)
    a = np.load(tmp_path / "gc.npz")
    assert a["est_pixels"].tolist() == [[6, 6], [6, 0]] and a["est_conf_sum"][1, 0] == 2.5
    assert a["est_conf_hist"][0, 1, 10] == 6 and a["est_agree_clean"].sum() == 9
    entry.write_predictions(tmp_path / "p.npz", results, conds)
    p = np.load(tmp_path / "p.npz")
    assert p["group_id"].tolist() == ["s0", "s1"] and p["g00000"].shape == (2, 2, 3)
    assert (p["g00001"][1] == 255).all() and (p["g00001"][0] == 1).all()  # absent condition: 255
    parts = tmp_path / "parts"
    shards.write_part(parts, 0, 1, results)
    back = shards.read_parts(parts)
    assert set(back) == {"s0", "s1"} and np.array_equal(back["s0"]["pred"]["Day-RAIN"], results[0]["pred"]["Day-RAIN"])
    assert back["s1"]["estimators"]["Day-EXTRASUNNY"]["conf_sum"] == 2.5
    (parts / "part-00000-of-00001.npz").unlink()  # maps lost: the part is not trusted, its groups are redone
    assert shards.read_parts(parts) == {}


def test_estimators_csv_per_model_by_hand(tmp_path):
    """Two groups, clean + one adverse condition: AC, plain agreement, entropy, DoC and ATC by hand."""
    conds = ["Day-EXTRASUNNY", "Night-RAIN"]
    k = 19
    def hist(at):  # all of a group's 10 pixels in bin `at`
        h = [0] * counting.CONF_BINS
        h[at] = 10
        return h
    cm_clean = np.zeros((k, k), int)
    cm_clean[0, 0], cm_clean[1, 1], cm_clean[1, 0] = 6, 2, 2     # clean pixel accuracy 0.8, IoU 0.75 and 0.5
    cm_adv = np.zeros((k, k), int)
    cm_adv[0, 0], cm_adv[1, 0] = 6, 4                            # adverse: IoU 0.6 and 0
    results = []
    for g, (clean_bin, adv_bin) in enumerate([(950, 700), (750, 300)]):
        results.append({"group_id": f"s{g}", "xi": {}, "cm": {conds[0]: cm_clean.tolist(), conds[1]: cm_adv.tolist()},
                        "estimators": {conds[0]: {"pixels": 10, "conf_sum": 10 * clean_bin / 1000, "entropy_sum": 1.0,
                                                   "conf_hist": hist(clean_bin), "agree_clean": 10},
                                       conds[1]: {"pixels": 10, "conf_sum": 10 * adv_bin / 1000, "entropy_sum": 4.0,
                                                   "conf_hist": hist(adv_bin), "agree_clean": 3 + g}}})
    arrays = entry.write_group_counts(tmp_path / "group_counts.npz", results, conds)
    conv = {"mean_exclude": [], "absent": "nan", "min_images": 0, "min_pixels": 0}
    out = tables.write_estimators(tmp_path, "m", conds, {"clean": conds[0], "convention": conv}, arrays)
    adv = out["Night-RAIN"]
    assert adv["ac"] == pytest.approx(0.5) and adv["self_agreement"] == pytest.approx(7 / 20)
    assert adv["entropy"] == pytest.approx(1 - 8 / 20)
    assert adv["clean_miou"] == pytest.approx(0.625) and adv["gt_miou"] == pytest.approx(0.3)
    assert adv["doc"] == pytest.approx(0.625 + 0.5 - 0.85)
    # ATC, its threshold fitted on the other (held-out) scene's clean image, accuracy 0.8 in each: group 0 is
    # scored with group 1's threshold (clean pixels all at 0.75: 0.751), group 1 with group 0's (all at 0.95:
    # 0.951); the mean threshold 0.851. Adverse pixels at 0.70 and 0.30: none above either
    assert adv["atc_threshold"] == pytest.approx(0.851) and adv["atc"] == pytest.approx(0.0)
    assert adv["atc_rel"] == pytest.approx(0.0) and adv["ac_rel"] == pytest.approx(0.5 / 0.85)
    import pandas as pd

    table = pd.read_csv(tmp_path / "estimators.csv")
    assert list(table["condition"]) == conds and table.loc[0, "self_agreement"] == 1.0


def test_entry_written_from_counted_groups_by_hand(tmp_path):
    """Two groups counted by `group_counts` (the _Fixed model keeps half of class 0 at night), summed and
    written by `entry.write_outputs`: xi, IoU and agreement by hand, through the metrics' update_counts."""
    import json

    import pandas as pd

    clean, adverse = "Day-EXTRASUNNY", "Night-RAIN"
    images = {clean: np.full((4, 6, 3), 200, np.uint8), adverse: np.full((4, 6, 3), 20, np.uint8)}
    zeros = np.zeros((4, 6), np.uint8)
    conv = {"name": "strict", "absent": "nan", "mean_exclude": [], "agreement": "pooled", "rho_headline": "top_m",
            "min_images": 1, "min_pixels": 1}
    s = {"clean": clean, "tau_mass": 0.5, "class_ids": [0, 1], "convention": conv, "sampling": "all",
         "min_transmittance": 0.0, "resamples": 20, "confidence": 0.9, "seed": 0, "selections": ["top_m"], "m": 25}
    groups = [counting.group_counts({"group_id": f"g{i}", "present": [clean, adverse], "images": images, "pseudo": zeros,
                                     "own": {clean: zeros}}, _Fixed(), s, clean, True, 2, "fixed", "d") for i in range(2)]
    covered = {"groups_per_condition": {clean: 2, adverse: 2}, "groups_without_clean": 0}
    out = entry.write_outputs(tmp_path, entry.ModelEvaluation("d", "fixed", "ref", [clean, adverse], s, groups, covered))
    assert out["xi_mean"] == {clean: 1.0, adverse: 0.5}
    xi = pd.read_csv(tmp_path / tables.XI).set_index(["reference_model", "condition", "class_name"])
    for source in ("ref", counting.GT):
        row = xi.loc[(source, adverse, "road")]
        assert (row.xi, row.retained_pixels, row.reference_pixels, row.images, row.n_pairs) == (0.5, 24, 48, 2, 2)
        assert np.isnan(xi.loc[(source, adverse, "sidewalk")].xi) and xi.loc[(source, adverse, "mean")].xi == 0.5
    iou = pd.read_csv(tmp_path / tables.GT_IOU).set_index(["condition", "class_name"]).iou
    assert (iou[(adverse, "road")], iou[(adverse, "sidewalk")], iou[(adverse, "mean")], iou[(clean, "mean")]) == (0.5, 0, 0.25, 1)
    agree = pd.read_csv(tmp_path / tables.AGREEMENT, dtype={"pair_id": str}).set_index(["condition", "pair_id"])
    assert agree.loc[(adverse, "ALL")].agreement_reference == 0.5 and agree.loc[(adverse, "g1")].valid_pixels == 24
    frames = pd.read_csv(tmp_path / tables.FRAME_COUNTS)
    assert frames.groupby("class_name")[["clean_count", "adv_count"]].sum().to_dict("index") == {
        "road": {"clean_count": 48, "adv_count": 24}, "sidewalk": {"clean_count": 0, "adv_count": 24}}
    summary = json.loads((tmp_path / entry.SUMMARY).read_text())
    assert summary["gt_miou"] == {clean: 1.0, adverse: 0.25} and summary["n_pairs"] == {clean: 2, adverse: 2}
    assert summary["xi_mean_gt"] == {clean: 1.0, adverse: 0.5} and summary["groups_per_condition"][adverse] == 2
    assert set(registry.result_files()) <= {p.name for p in tmp_path.iterdir()}
