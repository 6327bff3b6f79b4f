"""Issue 49's missing estimators from the same forward pass as xi, each against a hand computation: the nuclear
norm of the softmax matrix (Deng et al., ICML 2023), the energy score (mean logsumexp of the logits) and ATC with
its share and accuracy over the same (labelled) pixels."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pairedgta.cityscapes import IGNORE_INDEX, NUM_CLASSES
from pairedgta.evaluation import counting, entry, tables
from pairedgta.metrics.estimators import EstimatorCounts, energy_score, nuclear_norm_score
from pairedgta.models.base import Segmenter

K = NUM_CLASSES


def _counts(grams, energy, pixels):
    """EstimatorCounts of one condition over groups with the given Grams, energy sums and pixel counts."""
    g = len(pixels)
    z = np.zeros((g, 1))
    return EstimatorCounts("m", ("c",), np.asarray(pixels, float).reshape(g, 1), z, z, np.zeros((g, 1, 10)), z,
                           gram=np.asarray(grams, float).reshape(g, 1, K, K),
                           energy_sum=np.asarray(energy, float).reshape(g, 1))


def test_nuclear_norm_of_pooled_images_is_the_sum_of_singular_values_normalised():
    rng = np.random.default_rng(0)
    images = [rng.dirichlet(np.full(K, 0.3), size=n) for n in (7, 5)]   # pixels x K softmax matrices
    c = _counts([p.T @ p for p in images], [0, 0], [7, 5])
    stacked = np.vstack(images)
    expected = np.linalg.svd(stacked, compute_uv=False).sum() / math.sqrt(min(12, K) * 12)
    # fewer pixels than classes: the Gram's zero eigenvalues come out at ~1e-17, whose roots add ~1e-8
    assert nuclear_norm_score(c, np.ones((1, 2)))[0, 0] == pytest.approx(expected, rel=1e-7)
    # the normalisation: confident and evenly spread over the K classes scores 1, uniform scores 1 / K
    onehot = np.eye(K)[np.arange(3 * K) % K]
    uniform = np.full((3 * K, K), 1.0 / K)
    for p, value in ((onehot, 1.0), (uniform, 1.0 / K)):
        assert nuclear_norm_score(_counts([p.T @ p], [0], [3 * K]), np.ones((1, 1)))[0, 0] == pytest.approx(value)
    # a bootstrap weight doubles a group's pixels and its Gram alike
    doubled = nuclear_norm_score(c, np.array([[2.0, 0.0]]))[0, 0]
    single = np.linalg.svd(np.vstack([images[0]] * 2), compute_uv=False).sum() / math.sqrt(min(14, K) * 14)
    assert doubled == pytest.approx(single, rel=1e-7)


def test_energy_is_the_pooled_mean_logsumexp_and_nan_without_logits():
    c = _counts(np.zeros((2, K, K)), [30.0, 10.0], [10, 10])
    assert energy_score(c, np.ones((1, 2)))[0, 0] == pytest.approx(2.0)
    assert math.isnan(energy_score(_counts(np.zeros((1, K, K)), [np.nan], [4]), np.ones((1, 1)))[0, 0])


@pytest.mark.parametrize("name", ["tiny_segformer", "tiny_ddrnet"])
def test_gram_and_energy_come_from_the_same_forward_by_hand(name):
    """The Gram of each image's probabilities and the logsumexp of its logits, against float64 by hand; the
    labels and confidences are those of the plain prediction, bit for bit."""
    from pairedgta.models import build_model

    seg = build_model(name, batch_size=2)
    x = np.random.default_rng(1).integers(0, 256, (3, 32, 64, 3), dtype=np.uint8)
    maps = seg.predict_maps(x, energy=True, gram=True)
    plain = seg.predict_maps(x)
    assert torch.equal(maps.labels, plain.labels) and torch.equal(maps.confidence, plain.confidence)
    assert torch.equal(maps.entropy, plain.entropy)
    probs = seg.predict_proba(x).double()
    assert maps.gram.shape == (3, K, K) and maps.gram.dtype == torch.float64
    assert torch.allclose(maps.gram, torch.einsum("bkhw,blhw->bkl", probs, probs), rtol=1e-5, atol=1e-6)
    with torch.inference_mode():
        logits = seg._logits(seg.to_device(x))
        if logits.shape[-2:] != (32, 64):
            logits = torch.nn.functional.interpolate(logits.float(), size=(32, 64), mode="bilinear", align_corners=False)
    assert torch.allclose(maps.energy.double(), logits.double().logsumexp(1), rtol=1e-5, atol=1e-5)  # float32
    assert torch.allclose(logits.softmax(1).double(), probs, atol=1e-4)  # the logits of these probabilities (batched as one)


class _Distribution(Segmenter):
    """A family whose output is already a distribution (as Mask2Former's): no logits to take an energy of."""

    def __init__(self) -> None:
        super().__init__("dist", torch.nn.Identity())

    def _logits(self, images):
        raise NotImplementedError

    def _probabilities(self, images):
        p = torch.zeros(images.shape[0], K, *images.shape[-2:])
        p[:, 0], p[:, 1] = 0.75, 0.25
        return p


def test_a_family_without_logits_has_no_energy_but_a_gram():
    maps = _Distribution().predict_maps(np.zeros((1, 2, 3, 3), np.uint8), energy=True, gram=True)
    assert maps.energy is None
    assert maps.gram[0, 0, 0] == pytest.approx(6 * 0.75 ** 2) and maps.gram[0, 0, 1] == pytest.approx(6 * 0.75 * 0.25)


class _Fixed:
    """Class 0 everywhere with probability 0.875 on the left half of each image, 0.625 on the right (binary-exact)."""

    name = "fixed"

    def predict_with_entropy(self, images):
        b, h, w, _ = images.shape
        conf = torch.full((b, h, w), 0.875)
        conf[..., w // 2 :] = 0.625
        return torch.zeros((b, h, w), dtype=torch.long), conf, torch.zeros((b, h, w))


def test_atc_share_is_counted_over_the_labelled_pixels_its_accuracy_is():
    """The clean image's right half is void in its labels: its confidences stay out of the labelled histogram of
    every condition, as its pixels stay out of the clean accuracy that ATC's threshold is fitted to."""
    clean, adverse = "Day-EXTRASUNNY", "Night-RAIN"
    truth = np.zeros((4, 6), np.uint8)
    truth[:, 3:] = IGNORE_INDEX
    item = {"group_id": "g0", "present": [clean, adverse], "images": {c: np.zeros((4, 6, 3), np.uint8) for c in
                                                                       (clean, adverse)},
            "pseudo": np.zeros((4, 6), np.uint8), "own": {clean: truth}}
    out = counting.group_counts(item, _Fixed(), {"clean": clean, "tau_mass": 0.5, "class_ids": [0]}, clean, True, 2,
                                "fixed", "d")
    for c in (clean, adverse):
        e = out["estimators"][c]
        assert np.asarray(e["conf_hist"])[[625, 875]].tolist() == [12, 12]           # every pixel
        assert np.asarray(e["conf_hist_labelled"])[[625, 875]].tolist() == [0, 12]   # the labelled ones only
    assert out["cm"][clean][0][0] == 12                                              # the accuracy's pixels


def test_estimators_csv_has_the_new_estimators_and_says_where_there_are_no_logits(tmp_path):
    conds = ["Day-EXTRASUNNY", "Night-RAIN"]
    hist = [0] * counting.CONF_BINS
    hist[900] = 4
    onehot = np.eye(K)[np.arange(4) % 2]                       # 4 pixels, two classes: ||P||_* = 2 sqrt(2)
    results = []
    for g in range(2):
        cm = np.zeros((K, K), int)
        cm[0, 0] = 4
        results.append({"group_id": f"s{g}", "xi": {}, "cm": {c: cm.tolist() for c in conds},
                        "estimators": {c: {"pixels": 4, "conf_sum": 3.6, "entropy_sum": 0.0, "conf_hist": hist,
                                           "agree_clean": 4, "conf_hist_labelled": hist} for c in conds},
                        "nuclear_norm": {c: (onehot.T @ onehot).tolist() for c in conds},
                        "energy": {conds[0]: 8.0, conds[1]: None}})
    from pairedgta.evaluation import registry

    arrays = entry.write_group_counts(tmp_path / "group_counts.npz", results, conds)
    assert {"est_gram", "est_energy_sum", "est_conf_hist_labelled"} <= set(arrays) and registry.metrics()
    conv = {"mean_exclude": [], "absent": "nan", "min_images": 0, "min_pixels": 0}
    out = tables.write_estimators(tmp_path, "m", conds, {"clean": conds[0], "convention": conv}, arrays)
    # 8 pixels of two classes: singular values 2 and 2, over sqrt(min(8, K) * 8) = 8
    assert out[conds[0]]["nuclear_norm"] == pytest.approx(0.5) and out[conds[0]]["energy"] == pytest.approx(2.0)
    assert math.isnan(out[conds[1]]["energy"])
    import pandas as pd

    table = pd.read_csv(tmp_path / tables.ESTIMATORS).set_index("condition")
    assert table["has_logits"].tolist() == [True, False] and table.loc[conds[0], "nuclear_norm"] == pytest.approx(0.5)
