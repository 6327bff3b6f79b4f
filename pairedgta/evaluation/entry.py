"""One model's evaluate entry from its groups' records: every registered metric's tables
(`registry.METRICS`), the arrays they contribute to group_counts.npz, the label maps (predictions.npz) and
summary.json. The entry's own files are named in `entry_files`, the metrics' files by their metrics.

A model whose label space cannot predict some Cityscapes classes (`label_space`: a model source with
model.labels=ade20k, coco_panoptic or a TSV that maps no channel to them) has those classes' xi and IoU NaN with
the reason `cannot predict (label space <space>)` in xi.csv and gt_iou.csv (a `reason` column, written only in
such an entry), its class-wise means over the classes it can predict, and summary.json's `label_space` and
`unpredictable_classes`; both keys are absent where the model can predict every class (every zoo model), whose
files are as they were before these keys existed."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from pairedgta.cityscapes import IGNORE_INDEX
from pairedgta.datasets import PairedDataset
from pairedgta.evaluation.entry_files import GROUP_COUNTS, PREDICTIONS, SUMMARY
from pairedgta.evaluation.inputs import sampled_conditions
from pairedgta.evaluation.metric import Metric, ModelEvaluation
from pairedgta.jsonio import write_json, write_npz

log = logging.getLogger("pairedgta.evaluate")

CONFIDENCE_STEP = 2  # predictions.npz keeps the max probability at 1/2 resolution, uint8 (counting.confidence_thumbnail)
# The layout summary.json and group_counts.npz have had since evaluate VERSION 8, which these files keep byte for
# byte; what a metric registered since adds follows, in registry order.
SUMMARY_ORDER = ("model", "reference_model", "dataset", "convention", "sampling", "min_transmittance", "xi_mean",
                 "xi_mean_gt", "rho_valid", "rho_valid_headline", "gt_miou", "agreement", "n_pairs",
                 "groups_per_condition", "groups_without_clean", "estimators", "sampling_seed")
ARRAY_ORDER = ("group_id", "conditions", "present", "cm_present", "cm", "pseudo_label_retained",
               "pseudo_label_reference", "ground_truth_retained", "ground_truth_reference", "est_pixels",
               "est_conf_sum", "est_entropy_sum", "est_conf_hist", "est_agree_clean")


def in_order(d: dict[str, Any], order: tuple[str, ...]) -> dict[str, Any]:
    """`d` with the keys of `order` first, in that order, then the others as they were added."""
    return {**{k: d[k] for k in order if k in d}, **{k: v for k, v in d.items() if k not in order}}


def label_space(model_cfg: dict[str, Any]) -> tuple[str, tuple[str, ...]]:
    """(model.labels, the Cityscapes classes it cannot predict) of a model source, from its config alone (no
    torch, no model: a shard merge builds none); ("", ()) for a zoo family, which predicts the 19 classes."""
    from pairedgta.models import is_source
    from pairedgta.models.labels import resolve_labels

    if not is_source(model_cfg):
        return "", ()
    labels = resolve_labels(model_cfg.get("labels"), where=f"model ({model_cfg.get('name')})")
    return labels.space, labels.unpredictable


def write_outputs(out: Path, e: ModelEvaluation, ms: list[Metric] | None = None,
                  predictions: PredictionWriter | None = None) -> dict[str, Any]:
    """Every file of the entry into `out`, each registered metric's through its `write`; returns the summary.
    `predictions`: the label maps' archive written while evaluate counted (else written here from `e.groups`)."""
    from pairedgta.evaluation import registry

    ms = registry.metrics() if ms is None else ms
    s = e.settings
    arrays = write_group_counts(out / GROUP_COUNTS, e.groups, e.conditions, ms)
    if predictions is not None:
        predictions.close([r["group_id"] for r in e.groups])
    else:
        write_predictions(out / PREDICTIONS, e.groups, e.conditions)
    summary: dict[str, Any] = {"model": e.model, "reference_model": e.reference_model, "dataset": e.dataset,
                               "convention": s["convention"], "sampling": s["sampling"],
                               "min_transmittance": s["min_transmittance"],
                               **{k: {} for m in ms for k in m.summary_keys}, **e.coverage}
    if s["sampling"] == "random_one":
        summary["sampling_seed"] = s["sampling_seed"]
    if e.unpredictable:  # left out of xi_mean, xi_mean_gt and gt_miou; absent: every class can be predicted
        summary["label_space"] = e.label_space
        summary["unpredictable_classes"] = list(e.unpredictable)
    for m in ms:
        m.write(out, e, summary, arrays)
    summary = in_order(summary, SUMMARY_ORDER)
    write_json(out / SUMMARY, summary)
    return summary


def write_group_counts(path: Path, results: list[dict[str, Any]], conditions: list[str],
                       ms: list[Metric] | None = None) -> dict[str, np.ndarray]:
    """What a paired bootstrap over groups needs, per group g and condition i: the registered metrics' arrays
    (`Metric.arrays`: `present[g, i]`, the xi counts, the confusion matrices, the estimators' sums, ...) beside
    `group_id` and `conditions`. No pickle is needed to read it back."""
    from pairedgta.evaluation import registry

    arrays: dict[str, np.ndarray] = {"group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
                                     "conditions": np.array(conditions, dtype=str)}
    for m in registry.metrics() if ms is None else ms:
        arrays.update(m.arrays(results, conditions))
    arrays = in_order(arrays, ARRAY_ORDER)
    write_npz(path, arrays)  # built in memory, then one atomic write: no ZipFile left open by a failed write
    return arrays


def read_summary(path: Path) -> dict[str, Any]:
    return json.loads((path / SUMMARY).read_text())


def read_group_counts(path: Path) -> dict[str, np.ndarray]:
    """Per-group counts (`write_group_counts`); empty for entries written before evaluate VERSION 4."""
    path = path / GROUP_COUNTS
    if not path.is_file():
        return {}
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _map_stacks(g: int, r: dict[str, Any], conditions: list[str]) -> dict[str, np.ndarray]:
    """Group g's members of predictions.npz: `g<g>` its label maps, `c<g>` its max probabilities (below)."""
    arrays: dict[str, np.ndarray] = {}
    for key, maps, fill in (("g", r.get("pred") or {}, IGNORE_INDEX), ("c", r.get("conf") or {}, 0)):
        if not maps:
            continue
        shape = next(iter(maps.values())).shape
        stack = np.full((len(conditions), *shape), fill, dtype=np.uint8)
        for i, cond in enumerate(conditions):
            if cond in maps:
                stack[i] = maps[cond]
        arrays[f"{key}{g:05d}"] = stack
    return arrays


def write_predictions(path: Path, results: list[dict[str, Any]], conditions: list[str]) -> None:
    """Every group's predicted label maps (`g<index>`: C x H x W uint8, 255 where the condition's image is
    absent), so that estimators comparing models pixel by pixel (agreement between models, ALine) need no
    second inference pass. Label maps compress well: a few kB per image. Beside them (`c<index>`, C x H/2 x W/2
    uint8, 0 where absent) the max probability at CONFIDENCE_STEP, what the figures show of it, so that no figure
    predicts again (an entry from before has none: the figures then do). `PredictionWriter` writes the same
    archive while evaluate runs; this one is for groups merged from shard jobs, whose maps are all in memory."""
    arrays: dict[str, np.ndarray] = {"group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
                                     "conditions": np.array(conditions, dtype=str)}
    for g, r in enumerate(results):
        arrays.update(_map_stacks(g, r, conditions))
    write_npz(path, arrays)


class PredictionWriter:
    """predictions.npz written while evaluate counts: each group's maps are handed over as its results come
    (`add`) and compressed into the archive on a thread of their own (zlib releases the GIL), at zlib level 1.
    Compressing every map at the end at numpy's level 6 had been a third to a half of the stage on an H100
    at 2048x1024 (2.5 MB of maps an image; experiments/results/gpu_2026-11-27_*.md), and keeping them all until
    then grew the memory with the dataset. Up to `ahead` bytes of maps wait for the thread (1 GiB: about 45
    groups of nine 2048x1024 images), so a slower disk or zlib stalls the forwards only past that. The archive is
    the one `np.load` reads (the same members as `write_predictions`), under a temporary name until `close`;
    `abort` removes it. A failed write (a full disk) is raised by the next `add` or by `close`."""

    def __init__(self, path: Path, conditions: list[str], ahead: int = 2**30) -> None:
        import uuid
        import zipfile
        from concurrent.futures import ThreadPoolExecutor

        self.path, self.conditions, self.ahead = Path(path), list(conditions), ahead
        self.tmp = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex[:8]}.tmp")
        self.ids: list[str] = []
        self.pending: list[Any] = []
        self.file = open(self.tmp, "wb")  # noqa: SIM115 - closed by close/abort, whatever happens
        try:
            self.zip = zipfile.ZipFile(self.file, "w", zipfile.ZIP_DEFLATED, allowZip64=True, compresslevel=1)
        except BaseException:
            self._discard()
            raise
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="predictions")

    def _member(self, name: str, array: np.ndarray) -> None:
        with self.zip.open(f"{name}.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array(f, np.ascontiguousarray(array), allow_pickle=False)

    def _group(self, g: int, r: dict[str, Any]) -> None:
        for name, stack in _map_stacks(g, r, self.conditions).items():
            self._member(name, stack)

    def _wait(self, keep: int) -> None:
        while self.pending and (sum(n for _, n in self.pending) > keep or self.pending[0][0].done()):
            self.pending.pop(0)[0].result()  # a failed write is raised here

    def add(self, group_id: str, pred: dict[str, np.ndarray], conf: dict[str, np.ndarray]) -> None:
        size = sum(m.nbytes for maps in (pred, conf) for m in maps.values())
        self.pending.append((self.pool.submit(self._group, len(self.ids), {"pred": pred, "conf": conf}), size))
        self.ids.append(str(group_id))
        self._wait(self.ahead)

    def close(self, group_ids: list[str]) -> None:
        """The last groups, `group_id` and `conditions`, then the archive renamed into place. `group_ids`: the
        entry's groups in order, which must be the ones added, in the order added."""
        import os

        if [str(g) for g in group_ids] != self.ids:
            raise RuntimeError(f"{self.path}: the groups written ({len(self.ids)}) are not the entry's "
                               f"({len(group_ids)}), or not in its order")
        self._wait(0)
        self.pool.shutdown()
        self._member("group_id", np.array(self.ids, dtype=str))
        self._member("conditions", np.array(self.conditions, dtype=str))
        self.zip.close()
        self.file.close()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        """Nothing left behind: the thread stopped, the archive closed (its errors dropped) and removed."""
        self.pool.shutdown(wait=True, cancel_futures=True)
        try:
            self.zip.close()  # writes the central directory, which a full disk refuses: that is fine here
        except Exception:  # noqa: BLE001
            pass
        self._discard()

    def _discard(self) -> None:
        try:
            self.file.close()  # a buffered write the disk refuses raises here, the file closed all the same
        except OSError:
            pass
        self.tmp.unlink(missing_ok=True)


def read_prediction(path: Path, group_id: str, condition: str) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(labels H x W uint8, max probability H/2 x W/2 float in [0, 1] or None) of one image from an entry's
    predictions.npz; None where the file, the group or the image is not there."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            ids, conds = [str(g) for g in z["group_id"]], [str(c) for c in z["conditions"]]
            if group_id not in ids or condition not in conds:
                return None
            g, i = ids.index(group_id), conds.index(condition)
            if f"g{g:05d}" not in z.files:
                return None
            labels = z[f"g{g:05d}"][i]
            if (labels == IGNORE_INDEX).all():
                return None
            conf = z[f"c{g:05d}"][i].astype(np.float32) / 255.0 if f"c{g:05d}" in z.files else None
            return labels, conf
    except (OSError, ValueError, KeyError, EOFError):  # a damaged file: the figure predicts the image again
        log.warning("evaluate entry %s: cannot read its predictions; the figures predict them again", path.parent)
        return None


def coverage(dataset: PairedDataset, conditions: list[str], clean: str, model: str, sampling: str = "all",
             sampling_seed: int = 0) -> dict[str, Any]:
    """How many groups each condition's numbers average over (under evaluate.sampling=random_one, the
    groups that drew it); a warning when missing images make the conditions' groups differ."""
    groups = {c: 0 for c in conditions}
    available = dict(groups)
    without_clean = 0
    for g in dataset.groups:
        if clean not in g.images:
            without_clean += 1
            continue
        present = [c for c in conditions if c in g.images]
        for c in present:
            available[c] += 1
        for c in sampled_conditions(g.group_id, [clean] + [c for c in present if c != clean], clean, sampling, sampling_seed):
            groups[c] += c in groups
    if without_clean or len(set(available.values())) > 1:
        log.warning("evaluate [%s]: conditions are averaged over different groups: %s%s (a missing image "
                    "leaves its group out of that condition only; see summary.json groups_per_condition)",
                    model, ", ".join(f"{c} {n}" for c, n in groups.items()),
                    f"; {without_clean} group(s) without the clean image {clean} skipped" if without_clean else "")
    return {"groups_per_condition": groups, "groups_without_clean": without_clean}
