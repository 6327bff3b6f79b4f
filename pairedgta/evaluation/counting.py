"""One group's counts from one forward pass per image: per (reference source, condition) the retained
and reference pixels per class (xi), the confusion matrix against ground truth (IoU), the agreement
counts, the prediction mass phi per class (rho_valid) and the label-free estimators' sums. Plain numbers
only (a shard job's partial sums are lists of these), never the predictions' probabilities, so memory
does not grow with the image size times the number of images."""
from __future__ import annotations

from typing import Any

import numpy as np
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import LabelMaps, PairedDataset
from pairedgta.errors import DataError
from pairedgta.evaluation.inputs import GroupInputs, load_groups
from pairedgta.metrics import pixel_agreement, prediction_mass_from_labels, reference_consistency_counts
from pairedgta.metrics.segmentation import confusion_counts

PSEUDO_LABEL, GT = "pseudo_label", "ground_truth"  # the reference sources xi is measured against
CONF_BINS = 1000  # the max-probability histogram ATC's threshold is read from: edges k / 1000


def group_counts(item: dict[str, Any], segmenter: Any, s: dict[str, Any], reference: str, use_pl: bool,
                 batch: int, model: str, dataset_name: str) -> dict[str, Any]:
    """Everything evaluate keeps of one group (`item` from `GroupInputs`): `xi` per "<source>|<condition>"
    the retained and reference pixels per class, `cm` per condition the confusion matrix against its
    ground truth, `agreement` and `counts` (phi) rows, `estimators` sums and `pred` label maps."""
    clean, present = s["clean"], item["present"]
    images, pseudo_t = item["images"], item["pseudo"].astype(np.int64)
    own = item["own"]
    gt_t = own[reference].astype(np.int64) if reference in own else None
    visible = item.get("visible") or {}  # metric.min_transmittance: what each condition leaves visible

    def hide(label: np.ndarray | None, c: str) -> np.ndarray | None:
        return label if label is None or c not in visible else np.where(visible[c], label, IGNORE_INDEX)

    preds: dict[str, np.ndarray] = {}
    confs: dict[str, np.ndarray] = {}
    entropies: dict[str, np.ndarray] = {}
    for start in range(0, len(present), batch):
        names = present[start : start + batch]
        labels, conf, entropy = segmenter.predict_with_entropy(np.stack([images[c] for c in names]))
        labels, conf, entropy = labels.numpy(), np.asarray(conf), np.asarray(entropy)
        for i, c in enumerate(names):
            preds[c], confs[c], entropies[c] = labels[i], conf[i], entropy[i]

    def mass(c: str, seen: str) -> np.ndarray:
        """phi counts of c's prediction over the pixels visible in condition `seen`."""
        conf = confs[c] if seen not in visible else np.where(visible[seen], confs[c], -1.0)
        return prediction_mass_from_labels(preds[c], conf, NUM_CLASSES, s["tau_mass"]).numpy()[0]

    out: dict[str, Any] = {"group_id": item["group_id"], "xi": {}, "cm": {}, "agreement": [], "counts": [],
                           "estimators": {c: estimator_sums(preds[c], confs[c], entropies[c], preds[clean]) for c in present},
                           "pred": {c: preds[c].astype(np.uint8) for c in present}}
    for c in present:
        pred = preds[c]
        pseudo_c = hide(pseudo_t, c)
        if use_pl:
            r, t = reference_consistency_counts(pseudo_c, pred, NUM_CLASSES, IGNORE_INDEX)
            out["xi"][f"{PSEUDO_LABEL}|{c}"] = [r.tolist(), t.tolist()]
        if gt_t is not None:
            r, t = reference_consistency_counts(hide(gt_t, c), pred, NUM_CLASSES, IGNORE_INDEX)
            out["xi"][f"{GT}|{c}"] = [r.tolist(), t.tolist()]
        # IoU of condition c needs c's own truth; the reference's truth stands in only where the
        # dataset's labels are those of the reference frame (e.g. ACDC labels the adverse frame
        # only: they are never used as reference truth nor for the reference image)
        target = hide(own[c].astype(np.int64) if c in own else gt_t, c)
        if target is not None:
            out["cm"][c] = confusion_counts(target, pred, NUM_CLASSES, IGNORE_INDEX).tolist()
        agree_ref, valid = pixel_agreement(pred, pseudo_c, pseudo_c, IGNORE_INDEX)
        agree_clean, _ = pixel_agreement(pred, preds[clean], pseudo_c, IGNORE_INDEX)
        out["agreement"].append({
            "model": model, "condition": c, "pair_id": item["group_id"], "valid_pixels": valid,
            "agree_reference_pixels": agree_ref, "agree_clean_pixels": agree_clean,
        })
        if c != clean:
            clean_mass, adv_mass = mass(clean, c), mass(c, c)
            for k in s["class_ids"]:
                out["counts"].append({
                    "dataset": dataset_name, "model": model, "class_name": CLASS_NAMES[k], "pair_id": item["group_id"],
                    "condition": c, "clean_count": int(clean_mass[k]), "adv_count": int(adv_mass[k]),
                })
    return out


def estimator_sums(pred: np.ndarray, conf: np.ndarray, entropy: np.ndarray, clean_pred: np.ndarray) -> dict[str, Any]:
    """What the label-free estimators of accuracy under shift need of one image, as sums over all its pixels
    (no labels, no confidence filter): pixel count, summed max probability (AC, DoC), summed normalised
    entropy, the max-probability histogram (ATC) and the pixels predicted as on the clean image (plain
    agreement). Sums, so that groups add up and the bootstrap resamples them."""
    bins = np.minimum((np.asarray(conf, np.float64) * CONF_BINS).astype(np.int64), CONF_BINS - 1)
    return {"pixels": int(pred.size), "conf_sum": float(np.sum(conf, dtype=np.float64)),
            "entropy_sum": float(np.sum(entropy, dtype=np.float64)),
            "conf_hist": np.bincount(bins.ravel(), minlength=CONF_BINS).tolist(),
            "agree_clean": int((pred == clean_pred).sum())}


def count_groups(dataset: PairedDataset, labels: LabelMaps, segmenter: Any, s: dict[str, Any], conditions: list[str],
                 groups: list[Any], batch: int, workers: int) -> list[dict[str, Any]]:
    """`group_counts` of `groups` (those with the clean image), under the metric settings `s`, images
    decoded by `workers` DataLoader workers."""
    clean = s["clean"]
    order = [clean] + [c for c in conditions if c != clean]
    use_pl = s["reference_mode"] in ("pseudo_label", "both")
    use_gt = s["reference_mode"] in ("ground_truth", "both")
    inputs = GroupInputs(dataset, groups, order, clean, labels, use_gt, s["sampling"], s["sampling_seed"],
                         s["min_transmittance"])
    results = []
    for item in tqdm(load_groups(inputs, workers), total=len(groups), desc=f"evaluate [{segmenter.name}]", unit="group"):
        if "error" in item:
            raise DataError(item["error"])
        if item["present"]:
            results.append(group_counts(item, segmenter, s, dataset.reference, use_pl, batch, segmenter.name,
                                        dataset.name))
    return results
