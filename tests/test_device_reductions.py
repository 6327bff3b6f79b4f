"""Evaluate's reductions moved from numpy on the host to torch on the model's device (issue 48): on CPU tensors
they must give exactly the numbers of the former host path, kept here verbatim as the reference, so that moving
them changed no output (the evaluate CSVs of a run are byte-identical) and a GPU runs the very same arithmetic."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.evaluation import counting, reductions
from pairedgta.metrics import pixel_agreement, prediction_mass_from_labels, reference_consistency_counts
from pairedgta.metrics.segmentation import confusion_counts
from pairedgta.models.base import normalised_entropy, normalised_entropy_

CLEAN = "Day-EXTRASUNNY"
CONDS = [CLEAN, "Day-RAIN", "Night-RAIN", "Sunset-FOGGY"]


# -- the former host path, verbatim (pairedgta/models/base.py and pairedgta/evaluation/counting.py before #48) --
def old_predict_proba(seg, images: np.ndarray) -> torch.Tensor:
    images = torch.from_numpy(images.astype(np.float32)).div_(255.0).permute(0, 3, 1, 2).float()
    outputs = []
    with torch.inference_mode():
        for start in range(0, images.shape[0], seg.batch_size):
            probs = seg._probabilities(images[start : start + seg.batch_size])
            assert bool(torch.isfinite(probs).all())
            outputs.append(probs.float().cpu())
    return torch.cat(outputs, dim=0)


def old_predict_with_entropy(seg, images):
    probs = old_predict_proba(seg, images)
    confidence, labels = probs.max(dim=1)
    return labels, confidence, normalised_entropy(probs)


def old_estimator_sums(pred, conf, entropy, clean_pred):
    bins = np.minimum((np.asarray(conf, np.float64) * 1000).astype(np.int64), 1000 - 1)
    return {"pixels": int(pred.size), "conf_sum": float(np.sum(conf, dtype=np.float64)),
            "entropy_sum": float(np.sum(entropy, dtype=np.float64)),
            "conf_hist": np.bincount(bins.ravel(), minlength=1000).tolist(),
            "agree_clean": int((pred == clean_pred).sum())}


def old_group_counts(item, predict_with_entropy, s, reference, use_pl, batch, model, dataset_name):
    clean, present = s["clean"], item["present"]
    images, pseudo_t = item["images"], item["pseudo"].astype(np.int64)
    own = item["own"]
    gt_t = own[reference].astype(np.int64) if reference in own else None
    visible = item.get("visible") or {}

    def hide(label, c):
        return label if label is None or c not in visible else np.where(visible[c], label, IGNORE_INDEX)

    preds, confs, entropies = {}, {}, {}
    for start in range(0, len(present), batch):
        names = present[start : start + batch]
        labels, conf, entropy = predict_with_entropy(np.stack([images[c] for c in names]))
        labels, conf, entropy = labels.numpy(), np.asarray(conf), np.asarray(entropy)
        for i, c in enumerate(names):
            preds[c], confs[c], entropies[c] = labels[i], conf[i], entropy[i]

    def mass(c, seen):
        conf = confs[c] if seen not in visible else np.where(visible[seen], confs[c], -1.0)
        return prediction_mass_from_labels(preds[c], conf, NUM_CLASSES, s["tau_mass"]).numpy()[0]

    out = {"group_id": item["group_id"], "xi": {}, "cm": {}, "agreement": [], "counts": [],
           "estimators": {c: old_estimator_sums(preds[c], confs[c], entropies[c], preds[clean]) for c in present},
           "pred": {c: preds[c].astype(np.uint8) for c in present}}
    for c in present:
        pred = preds[c]
        pseudo_c = hide(pseudo_t, c)
        if use_pl:
            r, t = reference_consistency_counts(pseudo_c, pred, NUM_CLASSES, IGNORE_INDEX)
            out["xi"][f"pseudo_label|{c}"] = [r.tolist(), t.tolist()]
        if gt_t is not None:
            r, t = reference_consistency_counts(hide(gt_t, c), pred, NUM_CLASSES, IGNORE_INDEX)
            out["xi"][f"ground_truth|{c}"] = [r.tolist(), t.tolist()]
        target = hide(own[c].astype(np.int64) if c in own else gt_t, c)
        if target is not None:
            out["cm"][c] = confusion_counts(target, pred, NUM_CLASSES, IGNORE_INDEX).tolist()
        agree_ref, valid = pixel_agreement(pred, pseudo_c, pseudo_c, IGNORE_INDEX)
        agree_clean, _ = pixel_agreement(pred, preds[clean], pseudo_c, IGNORE_INDEX)
        out["agreement"].append({"model": model, "condition": c, "pair_id": item["group_id"], "valid_pixels": valid,
                                 "agree_reference_pixels": agree_ref, "agree_clean_pixels": agree_clean})
        if c != clean:
            clean_mass, adv_mass = mass(clean, c), mass(c, c)
            for k in s["class_ids"]:
                out["counts"].append({"dataset": dataset_name, "model": model, "class_name": CLASS_NAMES[k],
                                      "pair_id": item["group_id"], "condition": c, "clean_count": int(clean_mass[k]),
                                      "adv_count": int(adv_mass[k])})
    return out


# -- stand-ins ------------------------------------------------------------------------------------------------
class RandomProbs:
    """Fixed random distributions per image (seeded by its pixels): peaky and flat pixels, exact ties, and
    probabilities small enough that entropy sums round differently in another order."""

    name = "random"

    def __init__(self, scale: float = 6.0) -> None:
        self.scale = scale

    def probs(self, images: np.ndarray) -> torch.Tensor:
        out = []
        for im in images:
            g = torch.Generator().manual_seed(int(np.asarray(im, dtype=np.int64).sum()) % 2**31)
            logits = torch.randn(NUM_CLASSES, *im.shape[:2], generator=g) * self.scale
            logits[:, :2, :3] = 0.0  # uniform pixels: every class ties
            out.append(logits.softmax(0))
        return torch.stack(out)

    def predict_with_entropy(self, images):
        probs = self.probs(np.asarray(images))
        conf, labels = probs.max(dim=1)
        return labels, conf, normalised_entropy(probs)


def make_item(rng, h, w, conds, own=(), visible=False):
    images = {c: rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for c in conds}
    pseudo = rng.integers(0, NUM_CLASSES, (h, w)).astype(np.uint8)
    pseudo[rng.random((h, w)) < 0.3] = IGNORE_INDEX
    labels = {c: np.where(rng.random((h, w)) < 0.1, IGNORE_INDEX, rng.integers(0, NUM_CLASSES, (h, w))).astype(np.uint8)
              for c in own}
    item = {"group_id": "g7", "present": list(conds), "images": images, "pseudo": pseudo, "own": labels}
    if visible:
        seen = {c: rng.random((h, w)) < 0.8 for c in conds}
        item["visible"] = {c: seen[c] & seen[conds[0]] for c in conds}
    return item


def settings(tau=0.5):
    return {"clean": CLEAN, "tau_mass": tau, "class_ids": list(range(NUM_CLASSES))}


def assert_same(new, old):
    """Identical, floats included (== on Python floats, not approx), in everything the former path computed
    (the estimators added since, issue 49's, have their own tests: tests/test_dispersity_estimators.py)."""
    assert old.keys() <= new.keys()
    for key in ("group_id", "xi", "cm", "agreement", "counts"):
        assert new[key] == old[key], key
    assert {c: {k: e[k] for k in old["estimators"][c]} for c, e in new["estimators"].items()} == old["estimators"]
    assert new["pred"].keys() == old["pred"].keys()
    for c in old["pred"]:
        assert new["pred"][c].dtype == np.uint8 and np.array_equal(new["pred"][c], old["pred"][c])


# -- the tests --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("own, visible, use_pl, batch", [
    ((), False, True, 4),                          # pseudo-labels only
    ((CLEAN, "Night-RAIN"), True, True, 3),        # ground truth for two conditions, transmittance masks
    ((CLEAN,), False, False, 2),                   # reference truth stands in for every condition's IoU
])
def test_group_counts_equal_the_former_host_path_exactly(own, visible, use_pl, batch):
    rng = np.random.default_rng(3)
    item = make_item(rng, 48, 80, CONDS, own, visible)
    seg = RandomProbs()
    s = settings()
    new = counting.group_counts(item, seg, s, CLEAN, use_pl, batch, "m", "d")
    old = old_group_counts(item, seg.predict_with_entropy, s, CLEAN, use_pl, batch, "m", "d")
    assert_same(new, old)


@pytest.mark.parametrize("name", ["tiny_segformer", "tiny_ddrnet"])
def test_a_real_segmenter_on_the_device_path_equals_the_former_host_path(name):
    """The model's own path: uint8 to the device, the forward in the same batches, max and entropy per chunk,
    reductions there; against old predict_proba (float32 on the host, all chunks concatenated) + numpy."""
    from pairedgta.models import build_model

    seg = build_model(name, batch_size=2)
    rng = np.random.default_rng(0)
    item = make_item(rng, 64, 128, CONDS, own=(CLEAN,), visible=True)
    s = settings(tau=0.2)
    new = counting.group_counts(item, seg, s, CLEAN, True, 3, name, "d")
    old = old_group_counts(item, lambda x: old_predict_with_entropy(seg, x), s, CLEAN, True, 3, name, "d")
    assert_same(new, old)
    labels, conf, entropy = old_predict_with_entropy(seg, np.stack([item["images"][c] for c in CONDS]))
    maps = seg.predict_maps(np.stack([item["images"][c] for c in CONDS]))
    assert torch.equal(maps.labels.long(), labels) and torch.equal(maps.confidence, conf)
    assert torch.equal(maps.entropy, entropy)
    assert torch.equal(seg.predict_proba(item["images"][CLEAN][None]), old_predict_proba(seg, item["images"][CLEAN][None]))


@pytest.mark.parametrize("shape", [(1, 1), (4, 6), (7, 19), (64, 96), (100, 83), (256, 512), (3, 8192 + 136),
                                   (270, 480)])
def test_float_sums_add_in_numpys_order(shape):
    """Sums of many small float32 values in float64 depend on the order; block_sums + ordered_sum add as
    np.sum does, so entropy sums (values down to 1e-30) equal the host path's bit for bit."""
    rng = np.random.default_rng(sum(shape))
    x = (rng.random((3, *shape), dtype=np.float32) ** 9).astype(np.float32)
    x[0].flat[0] = 1e-30
    expected = [float(np.sum(x[i], dtype=np.float64)) for i in range(3)]
    assert reductions.image_sums(torch.from_numpy(x)) == expected


def test_entropy_in_place_is_bit_identical_and_sum_orders_do_differ():
    torch.manual_seed(0)
    probs = (torch.randn(2, NUM_CLASSES, 64, 128) * 8).softmax(1)
    h = normalised_entropy(probs)
    assert torch.equal(normalised_entropy_(probs.clone()), h)
    naive = [float(h[i].double().sum()) for i in range(2)] + [float(h[i].double().flip(0).sum()) for i in range(2)]
    ordered = reductions.image_sums(h) * 2
    assert ordered == [float(np.sum(h[i % 2].numpy(), dtype=np.float64)) for i in range(4)]
    assert naive != ordered  # the order matters for these values: the test above is not vacuous


def test_counting_kernels_match_numpy_bincount_and_drop_void():
    rng = np.random.default_rng(1)
    ref = rng.integers(0, NUM_CLASSES, (3, 20, 30)).astype(np.uint8)
    ref[:, :4] = IGNORE_INDEX
    pred = rng.integers(0, NUM_CLASSES, (3, 20, 30)).astype(np.uint8)
    xi = reductions.xi_counts(torch.from_numpy(ref), torch.from_numpy(pred)).numpy()
    cm = reductions.confusion(torch.from_numpy(ref), torch.from_numpy(pred)).numpy()
    for i in range(3):
        r, t = reference_consistency_counts(ref[i], pred[i], NUM_CLASSES)
        assert xi[i, :, 1].tolist() == r.tolist() and xi[i].sum(1).tolist() == t.tolist()
        assert np.array_equal(cm[i], confusion_counts(ref[i], pred[i], NUM_CLASSES))
    assert cm.sum() == (ref != IGNORE_INDEX).sum()
    assert reductions.count(torch.tensor([0, 2, 2, 5]), 5).tolist() == [1, 0, 2, 0, 0]  # 5 = the dropped bin
    keys = torch.from_numpy(rng.integers(0, 39, 10_001))
    assert torch.equal(reductions.count(keys, 38, lanes=64), reductions.count(keys, 38))  # a GPU's spread-out bins


def test_confidence_histogram_bins_like_the_host_path_and_survives_nan():
    conf = torch.tensor([[[0.0, 0.0005, 0.001, 0.25], [0.5, 0.9995, 0.999999, 1.0]]])
    assert reductions.confidence_histogram(conf)[0].tolist() == old_estimator_sums(
        np.zeros((2, 4)), conf[0].numpy(), np.zeros((2, 4), np.float32), np.zeros((2, 4)))["conf_hist"]
    bad = reductions.confidence_histogram(torch.tensor([[[math.nan, 0.5]]]))  # reported by check_finite, later
    assert int(bad.sum()) == 2


def test_a_nan_model_is_reported_once_at_the_end_of_the_stage_not_per_batch():
    from pairedgta.errors import ModelError
    from pairedgta.models import build_model

    seg = build_model("tiny_ddrnet")
    with torch.no_grad():
        next(seg.module.parameters()).fill_(float("nan"))
    x = np.zeros((2, 64, 128, 3), np.uint8)
    seg.predict_maps(x)
    seg.predict_maps(x)  # no error yet: the flag stays on the device
    with pytest.raises(ModelError, match="outputs are not finite"):
        seg.check_finite()
    seg.check_finite()  # read and reset


@pytest.mark.parametrize("levels", [3, 16, None])
def test_max_and_label_is_torch_max_with_its_tie_breaking(levels):
    """The first maximal class on ties, as torch.max returns it (quantised scores tie often)."""
    from pairedgta.models.base import max_and_label

    g = torch.Generator().manual_seed(levels or 0)
    x = torch.rand(2, NUM_CLASSES, 33, 47, generator=g)
    x = (x * levels).round() / levels if levels else x.softmax(1)
    conf, labels = max_and_label(x)
    values, indices = x.max(dim=1)
    assert labels.dtype == torch.uint8 and torch.equal(conf, values) and torch.equal(labels.long(), indices)
