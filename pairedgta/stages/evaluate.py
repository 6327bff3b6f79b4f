"""Evaluate stage, per model: xi per condition and class (eq. class_reference_consistency), pixel
agreement, phi per image and class (eq. prediction_mass) and rho_valid (eq. valid_spearman), with
percentile-bootstrap intervals over images; ground-truth IoU per condition where that condition's
labels exist (or the reference's, when only the reference is labelled) and xi-vs-ground-truth only
where the reference condition itself is labelled.

Streaming: per image only a few per-class counts are kept (for the bootstrap and for rho), never
predictions, so memory does not grow with the image size times the number of images.
"""
from __future__ import annotations

import json
import logging
import math
import os
import shutil
import zlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, class_id
from pairedgta.datasets import PairedDataset, load_group_images, load_label, load_transmittance
from pairedgta.errors import ConfigError, DataError, PairedGTAError
from pairedgta.metrics.bootstrap import class_mean_ci, drop_zero_width
from pairedgta.metrics.conventions import convention_from_config, support_mask
from pairedgta.metrics import (
    reference_consistency_counts,
    SELECTIONS,
    ConfusionMatrix,
    ReferenceConsistency,
    aggregate_agreement,
    class_mean,
    mean_mask,
    prediction_mass_from_labels,
    ratio_ci,
)
from pairedgta.metrics.ranking import rho_rows as rho_valid_rows
from pairedgta.models import shared_segmenter
from pairedgta.cache import MANIFEST, canonical_json, stage_hash
from pairedgta.conditions import ConditionGrid, headline_condition
from pairedgta.jsonio import write_json
from pairedgta.stages.common import (
    Context,
    StageResult,
    inference_threads,
    model_config_from_hash,
    model_hash_config,
    run_cached,
    shard_keys,
    torch_threads,
)
from pairedgta.stages.pseudolabel import PseudoLabels

from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

log = logging.getLogger("pairedgta.evaluate")
VERSION = "8"  # 8: label-free estimator sums (est_* in group_counts.npz), estimators.csv, predictions.npz; 7: top-M rho_valid only over frames that show the class, no zero-width interval, xi.csv `classes`; 6: metric.min_transmittance (xi.csv column); 2: metric conventions recorded in every output; mIoU over TP+FP+FN > 0; 3: groups_per_condition under random_one
# 4: group_counts.npz (per-group counts: the bootstrap of a comparison across models resamples groups)
# 5: xi.csv `images`/`supported` (metric.min_images/min_pixels); no interval for a class seen in one image;
#    random_one draws a time of day, then a weather of it (the authors' loader)
GT = "ground_truth"


class EvaluateResult(StageResult):
    """One model's evaluate entry and the readers of its files (the only code that names them).
    `complete` is False for a shard job's partial result (nothing to read yet)."""

    complete: bool = True

    FILES = ("xi.csv", "pixel_agreement.csv", "frame_counts.csv", "rho_valid.csv", "gt_iou.csv", "summary.json",
             "group_counts.npz", "estimators.csv")

    def model_config(self) -> dict[str, Any]:
        """The model's composed config: as this run built it, or (an evaluation collected from the cache)
        buildable from its manifest (figures re-predict a few groups with it)."""
        if "model_config" in self.extra:
            return dict(self.extra["model_config"])
        return model_config_from_hash(self.manifest()["config"]["model"])

    @property
    def model(self) -> str:
        return str(self.model_config()["name"])

    def _csv(self, name: str) -> pd.DataFrame:
        path = self.path / name
        return pd.read_csv(path, dtype={"pair_id": str}) if path.is_file() else pd.DataFrame()

    def xi(self) -> pd.DataFrame:
        return self._csv("xi.csv")

    def rho(self) -> pd.DataFrame:
        return self._csv("rho_valid.csv")

    def frame_counts(self) -> pd.DataFrame:
        return self._csv("frame_counts.csv")

    def agreement(self) -> pd.DataFrame:
        return self._csv("pixel_agreement.csv")

    def gt_iou(self) -> pd.DataFrame:
        return self._csv("gt_iou.csv")

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / "summary.json").read_text())

    def group_counts(self) -> dict[str, np.ndarray]:
        """Per-group counts (see `write_group_counts`); empty for entries written before VERSION 4."""
        path = self.path / "group_counts.npz"
        if not path.is_file():
            return {}
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def artifacts(self) -> list[Path]:
        return [self.path / f for f in self.FILES if (self.path / f).is_file()]

    def metrics(self, per_class: bool = False, cfg: Mapping[str, Any] | None = None) -> dict[str, float]:
        """The MLflow view: xi_mean/<cond>, xi_gt_mean/<cond>, gt_miou/<cond>, agreement/<cond> and the
        headline condition's rho_valid/<sel>/<class> (`conditions.headline_condition`: plot.ranking.condition
        of the run's `cfg` when set, as the ranking figure shows); with `per_class` (tracking.class_metrics)
        also xi/<cond>/<class>, xi_gt/<cond>/<class> and rho_valid/<cond>/<sel>/<class>, ten times as many
        metrics (the xi table and xi.csv/rho_valid.csv hold them either way)."""
        metrics: dict[str, float] = {}
        for row in self.xi().itertuples():
            prefix = "xi" if row.reference_model != GT else "xi_gt"
            if row.class_name == "mean":
                metrics[f"{prefix}_mean/{row.condition}"] = row.xi
            elif per_class:
                metrics[f"{prefix}/{row.condition}/{row.class_name}"] = row.xi
        rho = self.rho()
        conds = list(dict.fromkeys(rho["condition"])) if not rho.empty else []
        main = headline_condition(conds, cfg or {})
        for row in rho.itertuples():
            if per_class:
                metrics[f"rho_valid/{row.condition}/{row.selection}/{row.class_name}"] = row.rho
            if row.condition == main:
                metrics[f"rho_valid/{row.selection}/{row.class_name}"] = row.rho
        summary = self.summary()
        for cond, v in summary.get("gt_miou", {}).items():
            metrics[f"gt_miou/{cond}"] = v
        for cond, v in summary.get("agreement", {}).items():
            metrics[f"agreement/{cond}"] = v
        for cond, values in summary.get("estimators", {}).items():
            metrics.update({f"estimator/{name}/{cond}": v for name, v in values.items()
                            if isinstance(v, (int, float)) and math.isfinite(v)})
        return metrics


def conditions_for(cfg: dict[str, Any], grid: ConditionGrid) -> list[str]:
    """The conditions an evaluation covers: `evaluate.conditions` (always with the reference), else all."""
    wanted = (cfg.get("evaluate") or {}).get("conditions")
    if not wanted:
        return list(grid.names)
    unknown = [c for c in wanted if c not in grid.names]
    if unknown:
        raise ConfigError(f"evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(grid.names)}")
    return [c for c in grid.names if c in wanted or c == grid.reference]


def find_cached(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: StageResult,
                exclude: set[str]) -> list[EvaluateResult]:
    """Every cached evaluation of this dataset and pseudo-labels under the same metric settings and
    conditions (e.g. the models of an earlier multirun over `model=`): the newest per model, except the
    models in `exclude`."""
    root = ctx.cache.root / "evaluate"
    if not root.is_dir():
        return []
    want_inputs = {"dataset": dataset_key, "pseudolabel": pseudo.key}
    grid = dataset.grid or ctx.grid
    settings = json.loads(canonical_json(metric_settings(ctx.cfg, grid.names, dataset.reference)))
    conditions = conditions_for(ctx.cfg, grid)
    found: dict[str, tuple[float, EvaluateResult]] = {}
    for manifest_path in root.glob(f"*/{MANIFEST}"):
        d = manifest_path.parent
        if d.name.startswith("."):
            continue
        try:
            m = json.loads(manifest_path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        cfg = m.get("config") or {}
        if m.get("inputs") != want_inputs or cfg.get("metric") != settings or cfg.get("conditions") != conditions:
            continue
        name = str((cfg.get("model") or {}).get("name"))
        if name in exclude:
            continue
        mtime = manifest_path.stat().st_mtime
        if name not in found or mtime > found[name][0]:
            found[name] = (mtime, EvaluateResult("evaluate", d.name, d, hit=True))
    return [r for _, r in sorted(found.values(), key=lambda t: t[1].key)]


class _Accumulator:
    """Per (reference source, condition): streaming xi plus the per-image counts the bootstrap needs."""

    def __init__(self, absent: str = "nan") -> None:
        self.metric = ReferenceConsistency(NUM_CLASSES, IGNORE_INDEX, absent)
        self.retained: list[np.ndarray] = []
        self.reference: list[np.ndarray] = []

    def add(self, retained: np.ndarray, reference: np.ndarray) -> None:
        """One image's per-class counts (from `group_counts`, possibly computed by a shard job)."""
        self.metric.retained += torch.from_numpy(retained.astype(np.int64))
        self.metric.reference += torch.from_numpy(reference.astype(np.int64))
        self.retained.append(retained.astype(np.int64))
        self.reference.append(reference.astype(np.int64))


def metric_settings(cfg: dict[str, Any], grid_names: list[str], reference: str) -> dict[str, Any]:
    metric = cfg["metric"]
    rho = metric.get("rho") or {}
    selections = list(rho.get("selections") or SELECTIONS)
    bad = [s for s in selections if s not in SELECTIONS]
    if bad:
        raise ConfigError(f"metric.rho.selections: unknown {bad}; use {list(SELECTIONS)}")
    classes = rho.get("classes")
    class_ids = list(range(NUM_CLASSES)) if not classes else [class_id(c) for c in classes]
    tau = float(metric.get("tau_mass", 0.9))
    if not 0.0 <= tau <= 1.0:
        raise ConfigError(f"metric.tau_mass={tau} must be in [0, 1]")
    m = int(rho.get("m", 25))
    if m < 1:
        raise ConfigError(f"metric.rho.m={m} must be >= 1")
    ref_mode = metric.get("reference", "both")
    if ref_mode not in ("pseudo_label", "ground_truth", "both"):
        raise ConfigError(f"metric.reference={ref_mode!r}; use pseudo_label, ground_truth or both")
    boot = metric.get("bootstrap") or {}
    clean = rho.get("clean_condition") or reference
    if clean not in grid_names:
        raise ConfigError(f"metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(grid_names)}")
    ev = cfg.get("evaluate") or {}
    sampling = str(ev.get("sampling") or "all")
    if sampling not in SAMPLINGS:
        raise ConfigError(f"evaluate.sampling={sampling!r}; use one of {', '.join(SAMPLINGS)}")
    min_t = float(metric.get("min_transmittance") or 0.0)
    if not 0.0 <= min_t < 1.0:
        raise ConfigError(f"metric.min_transmittance={min_t}; use a transmittance in [0, 1)")
    settings = {
        "tau_mass": tau, "m": m, "min_transmittance": min_t, "selections": selections, "class_ids": class_ids, "reference_mode": ref_mode,
        "resamples": int(boot.get("resamples", 1000)), "confidence": float(boot.get("confidence", 0.95)),
        "seed": int(boot.get("seed", 0)), "clean": clean,
        "convention": convention_from_config(metric, selections).as_dict(),
        "sampling": sampling,
        # only a random draw depends on the seed (so `seed=` alone does not invalidate sampling=all results)
        "sampling_seed": int(ev.get("sampling_seed") or 0) if sampling == "random_one" else 0,
    }
    return settings


SAMPLINGS = ("all", "random_one")


def sampled_conditions(group_id: str, present: list[str], clean: str, sampling: str, seed: int) -> list[str]:
    """The conditions of one group to evaluate: all, or the clean one plus one adverse condition drawn
    as the authors' loader draws it: a time of day uniformly (the part of the name before the first
    "-": Day, Sunset, Night), then one of that time's adverse weathers uniformly. On the paper's grid a
    Day condition is drawn for 1/3 of the groups, not 2/8. The draw depends only on (seed, group id), so
    it is reproducible and does not change when groups are added, reordered or split over shards."""
    if sampling == "all":
        return present
    adverse = [c for c in present if c != clean]
    if not adverse:
        return present
    by_time: dict[str, list[str]] = {}
    for c in adverse:
        by_time.setdefault(c.split("-", 1)[0], []).append(c)
    rng = np.random.default_rng([seed, zlib.crc32(str(group_id).encode())])
    weathers = list(by_time.values())[int(rng.integers(len(by_time)))]
    return [clean, weathers[int(rng.integers(len(weathers)))]]


class _GroupInputs:  # a map-style dataset for torch's DataLoader (__len__ + __getitem__)
    """Decodes one group's images and label maps, in DataLoader workers (`evaluate.num_workers`), so the
    model forward, not PNG decoding, bounds evaluation. Errors come back as values, so the main process
    raises the same one-line error a sequential run would."""

    def __init__(self, dataset: PairedDataset, groups: list[Any], order: list[str], clean: str,
                 pseudo: PseudoLabels, use_gt: bool, sampling: str = "all", sampling_seed: int = 0,
                 min_transmittance: float = 0.0) -> None:
        self.dataset, self.groups, self.order, self.clean = dataset, groups, order, clean
        self.labels, self.use_gt = pseudo.labels, use_gt
        self.sampling, self.sampling_seed = sampling, sampling_seed
        self.min_transmittance = min_transmittance

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, i: int) -> dict[str, Any]:
        try:
            return self._load(self.groups[i])
        except PairedGTAError as exc:
            return {"error": str(exc), "kind": type(exc).__name__}

    def _load(self, group: Any) -> dict[str, Any]:
        present = [c for c in self.order if c in group.images]
        if self.clean not in present:
            return {"group_id": group.group_id, "present": []}
        present = sampled_conditions(group.group_id, present, self.clean, self.sampling, self.sampling_seed)
        images = load_group_images(group, present)
        shape = images[self.clean].shape[:2]
        pl_path = self.labels.path(group.group_id)
        pseudo = load_label(pl_path)
        if pseudo.shape != shape:
            raise DataError(
                f"{pl_path}: pseudo-label is {pseudo.shape[1]}x{pseudo.shape[0]} but the images of group "
                f"{group.group_id} are {shape[1]}x{shape[0]}; rerun with force=[pseudolabel]"
            )
        own: dict[str, np.ndarray] = {}
        for c in present if self.use_gt else []:
            if c in group.labels:
                own[c] = load_label(group.labels[c])
                if own[c].shape != shape:
                    raise DataError(f"{group.labels[c]}: label map size differs from its image")
        return {"group_id": group.group_id, "present": present, "images": images, "pseudo": pseudo, "own": own,
                "visible": self._visible(group, present, shape)}

    def _visible(self, group: Any, present: list[str], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
        """metric.min_transmittance > 0: per condition, the pixels visible in it and in the clean image."""
        if self.min_transmittance <= 0.0:
            return {}
        seen: dict[str, np.ndarray] = {}
        for c in present:
            if c not in group.transmittance:
                raise DataError(f"group {group.group_id} of {self.dataset.root} has no transmittance map for {c}; "
                                "regenerate it with renderer=blender or synthetic, or set metric.min_transmittance=0")
            t = load_transmittance(group.transmittance[c])
            if t.shape != shape:
                raise DataError(f"{group.transmittance[c]}: transmittance map size differs from its image")
            seen[c] = t >= self.min_transmittance
        return {c: seen[c] & seen[self.clean] for c in present}


def decode_workers(value: Any, device: str) -> int:
    """`evaluate.num_workers`: a count, or auto = none on the CPU (the forward already uses every core;
    measured in experiments/bench_evaluate.py) and up to 4 beside a GPU."""
    if value in (None, "auto"):
        return 0 if device == "cpu" else min(4, os.cpu_count() or 1)
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"evaluate.num_workers={value!r}; use a whole number >= 0 or auto") from None
    if n < 0:
        raise ConfigError(f"evaluate.num_workers={n}; use a whole number >= 0 or auto")
    return n


def _identity(item: Any) -> Any:
    return item


def _loader(inputs: _GroupInputs, workers: int) -> Any:
    if workers < 1:
        return (inputs[i] for i in range(len(inputs)))
    return torch.utils.data.DataLoader(inputs, batch_size=None, shuffle=False, num_workers=workers,
                                       collate_fn=_identity, prefetch_factor=2, persistent_workers=False)


def group_counts(item: dict[str, Any], segmenter: Any, s: dict[str, Any], reference: str, use_pl: bool,
                 batch: int, model: str, dataset_name: str) -> dict[str, Any]:
    """Everything evaluate keeps of one group, as plain numbers (a shard's partial sums are lists of
    these): per (reference source, condition) the retained and reference pixel counts per class, the
    confusion matrix against ground truth per condition, the agreement counts and the phi counts."""
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
            out["xi"][f"pseudo_label|{c}"] = [r.tolist(), t.tolist()]
        if gt_t is not None:
            r, t = reference_consistency_counts(hide(gt_t, c), pred, NUM_CLASSES, IGNORE_INDEX)
            out["xi"][f"{GT}|{c}"] = [r.tolist(), t.tolist()]
        # IoU of condition c needs c's own truth; the reference's truth stands in only where the
        # dataset's labels are those of the reference frame (e.g. ACDC labels the adverse frame
        # only: they are never used as reference truth nor for the reference image)
        target = hide(own[c].astype(np.int64) if c in own else gt_t, c)
        if target is not None:
            cm = ConfusionMatrix(NUM_CLASSES)
            cm.update(target, pred)
            out["cm"][c] = cm.mat.tolist()
        valid = pseudo_c != IGNORE_INDEX
        agree_ref = int(((pred == pseudo_c) & valid).sum())
        agree_clean = int(((pred == preds[clean]) & valid).sum())
        out["agreement"].append({
            "model": model, "condition": c, "pair_id": item["group_id"], "valid_pixels": int(valid.sum()),
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


CONF_BINS = 1000  # the max-probability histogram ATC's threshold is read from: edges k / 1000


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


def count_groups(ctx: Context, dataset: PairedDataset, pseudo_labels: PseudoLabels, model_cfg: dict[str, Any],
                 conditions: list[str], groups: list[Any]) -> list[dict[str, Any]]:
    """`group_counts` of `groups`, images decoded by `evaluate.num_workers` DataLoader workers."""
    grid = dataset.grid or ctx.grid
    s = metric_settings(ctx.cfg, grid.names, dataset.reference)
    segmenter = shared_segmenter(model_cfg, device=ctx.cfg.get("device", "cpu"))
    clean = s["clean"]
    order = [clean] + [c for c in conditions if c != clean]
    use_pl = s["reference_mode"] in ("pseudo_label", "both")
    use_gt = s["reference_mode"] in ("ground_truth", "both")
    ecfg = ctx.cfg.get("evaluate") or {}
    batch = int(ecfg.get("batch_size", 4))
    workers = decode_workers(ecfg.get("num_workers", "auto"), str(ctx.cfg.get("device", "cpu")))
    inputs = _GroupInputs(dataset, groups, order, clean, pseudo_labels, use_gt, s["sampling"], s["sampling_seed"],
                          s["min_transmittance"])
    results = []
    with torch_threads(inference_threads(ctx.cfg)):
        for item in tqdm(_loader(inputs, workers), total=len(groups), desc=f"evaluate [{segmenter.name}]", unit="group"):
            if "error" in item:
                raise DataError(item["error"])
            if item["present"]:
                results.append(group_counts(item, segmenter, s, dataset.reference, use_pl, batch, segmenter.name,
                                            dataset.name))
    return results


def compute(
    ctx: Context, dataset: PairedDataset, pseudo_labels: PseudoLabels, model_cfg: dict[str, Any], conditions: list[str],
    reference_model: str, out: Path, parts: Path | None = None,
) -> dict[str, Any]:
    """Evaluate every group, or merge the partial sums that shard jobs left in `parts` and compute only
    the groups no shard covered; the outputs are the same either way (groups in dataset order)."""
    grid = dataset.grid or ctx.grid
    s = metric_settings(ctx.cfg, grid.names, dataset.reference)
    conv = s["convention"]
    log.info("evaluate: metric convention %s (absent classes %s, mean without %s, %s agreement, rho_valid headline %s), "
             "sampling %s", conv["name"], conv["absent"], list(conv["mean_exclude"]) or "none", conv["agreement"],
             conv["rho_headline"], s["sampling"])
    done = read_parts(parts) if parts is not None else {}
    missing = [g for g in dataset.groups if g.group_id not in done]
    if done:
        log.info("evaluate: merging %d group(s) from shard jobs, computing %d", len(done), len(missing))
    for r in count_groups(ctx, dataset, pseudo_labels, model_cfg, conditions, missing):
        done[r["group_id"]] = r
    results = [done[g.group_id] for g in dataset.groups if g.group_id in done]
    model = str(model_cfg["name"])
    counts = write_group_counts(out / "group_counts.npz", results, conditions)
    write_predictions(out / "predictions.npz", results, conditions)
    estimators = write_estimators(out, model, conditions, s, counts)
    acc: dict[tuple[str, str], _Accumulator] = {}
    gt_cm: dict[str, ConfusionMatrix] = {}
    agreement_rows: list[dict[str, Any]] = []
    count_rows: list[dict[str, Any]] = []
    for r in results:
        for key, (retained, reference) in r["xi"].items():
            source, cond = key.split("|", 1)
            acc.setdefault((source, cond), _Accumulator(conv["absent"])).add(np.asarray(retained), np.asarray(reference))
        for cond, mat in r["cm"].items():
            gt_cm.setdefault(cond, ConfusionMatrix(NUM_CLASSES)).mat += torch.tensor(mat, dtype=torch.long)
        for row in r["agreement"]:
            n = row["valid_pixels"]
            agreement_rows.append({**row, "agreement_reference": row["agree_reference_pixels"] / n if n else math.nan,
                                   "agreement_clean": row["agree_clean_pixels"] / n if n else math.nan})
        count_rows += r["counts"]
    return write_outputs(out, dataset, model, reference_model, conditions, s, acc, gt_cm, agreement_rows, count_rows,
                         {**coverage(dataset, conditions, s["clean"], model, s["sampling"], s["sampling_seed"]),
                          "estimators": estimators})


def write_estimators(out: Path, model: str, conditions: list[str], s: dict[str, Any],
                     arrays: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """estimators.csv: per condition the label-free estimators of this model (pairedgta.metrics.estimators;
    GDE needs the other models and is computed where they meet, the `estimators` figure) beside xi and the
    ground-truth targets where labels exist. AC, entropy and plain agreement use no label; DoC, ATC and the
    clean mIoU use the clean condition's ground truth, as their methods use labelled source data."""
    from pairedgta.metrics.estimators import EstimatorCounts, model_values
    from pairedgta.metrics.validity import GroupCounts

    clean, conv = s["clean"], s["convention"]
    n = len(arrays["group_id"])
    if clean not in conditions or not n:
        return {}
    g, c = GroupCounts.from_arrays(model, arrays), EstimatorCounts.from_arrays(model, arrays)
    include = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    values = model_values(g, c, np.ones((1, n)), clean, include, conv["absent"], conv["min_images"], conv["min_pixels"])
    rows = {cond: {"model": model, "condition": cond,
                   **{k: float(v[0, i]) for k, v in values.items() if k != "atc_threshold"},
                   "atc_threshold": float(values["atc_threshold"][0])} for i, cond in enumerate(conditions)}
    pd.DataFrame(list(rows.values())).to_csv(out / "estimators.csv", index=False)
    return {cond: {k: v for k, v in r.items() if k not in ("model", "condition")} for cond, r in rows.items()}


def write_group_counts(path: Path, results: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
    """What a paired bootstrap over groups needs, per group g and condition i: `present[g, i]`; for each
    reference source (`pseudo_label`, `ground_truth`) the retained and reference pixels per class
    (`<source>_retained[g, i, c]`, `<source>_reference[g, i, c]`); and the confusion matrix against the
    condition's own labels (`cm[g, i, truth, prediction]`, with `cm_present[g, i]`). Integers only: no
    pickle is needed to read it back."""
    G, C = len(results), len(conditions)
    arrays: dict[str, np.ndarray] = {
        "group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
        "conditions": np.array(conditions, dtype=str),
        "present": np.zeros((G, C), dtype=bool), "cm_present": np.zeros((G, C), dtype=bool),
        "cm": np.zeros((G, C, NUM_CLASSES, NUM_CLASSES), dtype=np.int64),
    }
    for source in ("pseudo_label", GT):
        arrays[f"{source}_retained"] = np.zeros((G, C, NUM_CLASSES), dtype=np.int64)
        arrays[f"{source}_reference"] = np.zeros((G, C, NUM_CLASSES), dtype=np.int64)
    arrays.update({"est_pixels": np.zeros((G, C), dtype=np.int64), "est_conf_sum": np.zeros((G, C)),
                   "est_entropy_sum": np.zeros((G, C)), "est_conf_hist": np.zeros((G, C, CONF_BINS), dtype=np.int64),
                   "est_agree_clean": np.zeros((G, C), dtype=np.int64)})
    index = {c: i for i, c in enumerate(conditions)}
    for g, r in enumerate(results):
        for cond, e in (r.get("estimators") or {}).items():
            if cond in index:
                for k in ("pixels", "conf_sum", "entropy_sum", "conf_hist", "agree_clean"):
                    arrays[f"est_{k}"][g, index[cond]] = e[k]
        for key, (retained, reference) in r["xi"].items():
            source, cond = key.split("|", 1)
            if cond in index:
                arrays["present"][g, index[cond]] = True
                arrays[f"{source}_retained"][g, index[cond]] = retained
                arrays[f"{source}_reference"][g, index[cond]] = reference
        for cond, mat in r["cm"].items():
            if cond in index:
                arrays["cm_present"][g, index[cond]] = True
                arrays["cm"][g, index[cond]] = np.asarray(mat, dtype=np.int64)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return arrays


def write_predictions(path: Path, results: list[dict[str, Any]], conditions: list[str]) -> None:
    """Every group's predicted label maps (`g<index>`: C x H x W uint8, 255 where the condition's image is
    absent), so that estimators comparing models pixel by pixel (agreement between models, GDE) need no
    second inference pass. Label maps compress well: a few kB per image."""
    arrays: dict[str, np.ndarray] = {"group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
                                     "conditions": np.array(conditions, dtype=str)}
    for g, r in enumerate(results):
        maps = r.get("pred") or {}
        if not maps:
            continue
        shape = next(iter(maps.values())).shape
        stack = np.full((len(conditions), *shape), IGNORE_INDEX, dtype=np.uint8)
        for i, cond in enumerate(conditions):
            if cond in maps:
                stack[i] = maps[cond]
        arrays[f"g{g:05d}"] = stack
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


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


# -- shards: partial sums of evaluate.shard i of evaluate.num_shards, merged by the unsharded run --------
def parts_dir(ctx: Context, key: str) -> Path:
    return ctx.cache.root / "evaluate" / f".parts-{key}"


def read_parts(parts: Path) -> dict[str, dict[str, Any]]:
    found: dict[str, dict[str, Any]] = {}
    for path in sorted(parts.glob("part-*.json")) if parts.is_dir() else []:
        try:
            rows = json.loads(path.read_text())
            with np.load(path.with_suffix(".npz"), allow_pickle=False) as maps:
                for i, r in enumerate(rows):
                    r["pred"] = {c: maps[f"{i}|{c}"] for c in r.pop("pred_conditions")}
            for r in rows:
                found[r["group_id"]] = r
        except (OSError, ValueError, json.JSONDecodeError, KeyError, TypeError):
            log.warning("evaluate: ignoring unreadable shard result %s (its groups are computed again)", path)
    return found


def write_part(parts: Path, shard: int, num: int, results: list[dict[str, Any]]) -> Path:
    """The shard's sums as JSON and its label maps beside it (`.npz`); the maps are written first, so a
    JSON file is only ever seen with its maps complete."""
    parts.mkdir(parents=True, exist_ok=True)
    path = parts / f"part-{shard:05d}-of-{num:05d}.json"
    maps = {f"{i}|{c}": m for i, r in enumerate(results) for c, m in (r.get("pred") or {}).items()}
    rows = [{**{k: v for k, v in r.items() if k != "pred"}, "pred_conditions": list(r.get("pred") or {})} for r in results]
    tmp_maps = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")
    with open(tmp_maps, "wb") as f:
        np.savez_compressed(f, **maps)
    os.replace(tmp_maps, path.with_suffix(".npz"))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(rows, default=_jsonable, allow_nan=False))
    os.replace(tmp, path)
    return path


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_outputs(out, dataset, model, reference_model, conditions, s, acc, gt_cm, agreement_rows, count_rows,
                  coverage=None) -> dict[str, Any]:
    conv = s["convention"]
    name = conv["name"]
    summary: dict[str, Any] = {"model": model, "reference_model": reference_model, "dataset": dataset.name,
                               "convention": conv, "sampling": s["sampling"], "min_transmittance": s["min_transmittance"],
                               "xi_mean": {}, "xi_mean_gt": {}, "rho_valid": {}, "rho_valid_headline": {},
                               "gt_miou": {}, "agreement": {}, "n_pairs": {}, **(coverage or {})}
    if s["sampling"] == "random_one":
        summary["sampling_seed"] = s["sampling_seed"]
    in_mean = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    xi_rows = []
    for (source, cond), a in sorted(acc.items(), key=lambda kv: (kv[0][0], conditions.index(kv[0][1]))):
        xi = a.metric.compute().numpy()
        retained, reference = np.stack(a.retained), np.stack(a.reference)
        lo, hi = ratio_ci(retained, reference, s["resamples"], s["confidence"], s["seed"], conv["absent"])
        images = (reference > 0).sum(axis=0)
        if conv["absent"] == "nan":
            # a class seen in one image: every resample that defines it gives the same ratio, so the
            # bootstrap cannot vary and a zero-width interval would claim certainty
            lo, hi = np.where(images < 2, np.nan, lo), np.where(images < 2, np.nan, hi)
        lo, hi = drop_zero_width(lo, hi)
        supported = support_mask(images, a.metric.reference.numpy(), conv["min_images"], conv["min_pixels"])
        ref_name = reference_model if source == "pseudo_label" else GT
        # which classes the mean covers: the convention's classes, minus the undefined (NaN) and unsupported ones
        included = in_mean & ~np.isnan(xi) & supported
        for k in range(NUM_CLASSES):
            xi_rows.append({
                "model": model, "reference_model": ref_name, "condition": cond, "class_id": k,
                "class_name": CLASS_NAMES[k], "xi": xi[k], "ci_low": lo[k], "ci_high": hi[k],
                "reference_pixels": int(a.metric.reference[k]), "retained_pixels": int(a.metric.retained[k]),
                "images": int(images[k]), "supported": bool(supported[k]),
                "in_mean": bool(included[k]), "n_pairs": len(a.retained), "convention": name,
                "min_transmittance": s["min_transmittance"], "classes": 1 if included[k] else 0,
            })
        # the class-wise mean under the convention, with its own bootstrap over images
        mean = class_mean(xi, included)
        mlo, mhi = drop_zero_width(*class_mean_ci(retained, reference, included, s["resamples"], s["confidence"],
                                                  s["seed"], conv["absent"]))
        xi_rows.append({
            "model": model, "reference_model": ref_name, "condition": cond, "class_id": -1, "class_name": "mean",
            "xi": mean, "ci_low": mlo, "ci_high": mhi,
            "reference_pixels": int(a.metric.reference.sum()), "retained_pixels": int(a.metric.retained.sum()),
            "images": len(a.retained), "supported": bool(included.any()), "in_mean": False, "n_pairs": len(a.retained), "convention": name,
            "min_transmittance": s["min_transmittance"], "classes": int(included.sum()),  # how many classes the mean covers
        })
        summary["xi_mean" if source == "pseudo_label" else "xi_mean_gt"][cond] = mean
        if source == "pseudo_label" or not summary["n_pairs"].get(cond):
            summary["n_pairs"][cond] = len(a.retained)
    pd.DataFrame(xi_rows).to_csv(out / "xi.csv", index=False)

    agree = pd.DataFrame(agreement_rows)
    totals = []
    for cond, g in agree.groupby("condition", sort=False):
        n = g["valid_pixels"].sum()
        totals.append({
            "model": model, "condition": cond, "pair_id": "ALL", "valid_pixels": int(n),
            "agree_reference_pixels": int(g["agree_reference_pixels"].sum()),
            "agree_clean_pixels": int(g["agree_clean_pixels"].sum()),
            "agreement_reference": aggregate_agreement(g["agree_reference_pixels"], g["valid_pixels"], conv["agreement"]),
            "agreement_clean": aggregate_agreement(g["agree_clean_pixels"], g["valid_pixels"], conv["agreement"]),
        })
        summary["agreement"][cond] = totals[-1]["agreement_reference"]
    agree = pd.concat([agree, pd.DataFrame(totals)], ignore_index=True)
    # per-image rows are ratios of one image; the ALL row aggregates them per the convention
    agree["aggregation"] = np.where(agree["pair_id"] == "ALL", conv["agreement"], "image")
    agree["convention"] = name
    agree.to_csv(out / "pixel_agreement.csv", index=False)

    counts = pd.DataFrame(count_rows, columns=["dataset", "model", "class_name", "pair_id", "condition", "clean_count", "adv_count"])
    counts.to_csv(out / "frame_counts.csv", index=False)
    rho_rows = []
    for (cls, cond), g in counts.groupby(["class_name", "condition"], sort=False):
        for r in rho_valid_rows(g["clean_count"].to_numpy(), g["adv_count"].to_numpy(), s["selections"], s["m"],
                                s["resamples"], s["confidence"], s["seed"], conv["rho_headline"]):
            rho_rows.append({"dataset": dataset.name, "model": model, "class_name": cls, "condition": cond, **r,
                             "convention": name})
            summary["rho_valid"].setdefault(cond, {}).setdefault(r["selection"], {})[cls] = r["rho"]
            if r["headline"]:
                summary["rho_valid_headline"].setdefault(cond, {})[cls] = r["rho"]
    pd.DataFrame(rho_rows, columns=["dataset", "model", "class_name", "condition", "selection", "m", "n_frames", "rho",
                                    "ci_low", "ci_high", "headline", "convention"]).to_csv(out / "rho_valid.csv", index=False)

    if gt_cm:
        rows = []
        for cond in conditions:
            if cond not in gt_cm:
                continue
            iou = gt_cm[cond].iou().numpy()
            for k in range(NUM_CLASSES):
                rows.append({"model": model, "condition": cond, "class_id": k, "class_name": CLASS_NAMES[k], "iou": iou[k]})
            miou = gt_cm[cond].miou()
            rows.append({"model": model, "condition": cond, "class_id": -1, "class_name": "mean", "iou": miou})
            summary["gt_miou"][cond] = miou
        pd.DataFrame(rows).to_csv(out / "gt_iou.csv", index=False)
    write_json(out / "summary.json", summary)
    return {"xi_mean": summary["xi_mean"]}


def run(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: PseudoLabels,
        model_cfg: dict[str, Any]) -> EvaluateResult:
    grid = dataset.grid or ctx.grid
    conditions = conditions_for(ctx.cfg, grid)
    settings = metric_settings(ctx.cfg, grid.names, dataset.reference)
    config = {"model": model_hash_config(model_cfg), "metric": settings, "conditions": conditions,
              "threads": inference_threads(ctx.cfg)}
    inputs = {"dataset": dataset_key, "pseudolabel": pseudo.key}
    reference_model = pseudo.reference_model()
    key = stage_hash("evaluate", VERSION, config, inputs)
    parts = parts_dir(ctx, key)
    partial = run_shard(ctx, dataset, pseudo, model_cfg, conditions, key, parts)
    if partial is not None:
        return partial
    result = run_cached(
        ctx, "evaluate", VERSION, config, inputs,
        lambda out: compute(ctx, dataset, pseudo, model_cfg, conditions, reference_model, out, parts=parts),
        label=f"[{model_cfg['name']}]", result_cls=EvaluateResult,
    )
    assert isinstance(result, EvaluateResult)
    result.extra["model_config"] = dict(model_cfg)  # what later readers (the qualitative figure) rebuild
    shutil.rmtree(parts, ignore_errors=True)  # merged into the entry
    return result


def run_shard(ctx: Context, dataset: PairedDataset, pseudo: PseudoLabels, model_cfg: dict[str, Any],
              conditions: list[str], key: str, parts: Path) -> EvaluateResult | None:
    """Shard i of N evaluates groups i, i+N, ... and stores their partial sums; None when there is
    nothing left to shard (unsharded run, cached entry, or every group now covered: then the caller
    merges them into the entry)."""
    num, shard = shard_keys(ctx.cfg.get("evaluate") or {}, "evaluate")
    if num == 1 or ctx.cache.is_hit("evaluate", key):
        return None
    if "evaluate" not in ctx.stages:
        raise PairedGTAError(f"evaluate [{model_cfg['name']}]: no cached output for this configuration; run it first, "
                             "e.g. stages=[evaluate]")
    mine = dataset.groups[shard::num]
    done = read_parts(parts)
    todo = [g for g in mine if g.group_id not in done]
    log.info("evaluate [%s] shard %d of %d: %d of %d groups (%d already done)", model_cfg["name"], shard, num,
             len(mine), len(dataset.groups), len(mine) - len(todo))
    if todo:
        results = count_groups(ctx, dataset, pseudo, model_cfg, conditions, todo)
        write_part(parts, shard, num, [done[g.group_id] for g in mine if g.group_id in done] + results)
    covered = read_parts(parts)
    if all(g.group_id in covered for g in dataset.groups):
        return None
    log.info("evaluate [%s]: %d of %d groups evaluated by shards so far; run the remaining shards, then without "
             "evaluate.shard to merge", model_cfg["name"], len(covered), len(dataset.groups))
    result = EvaluateResult("evaluate", key, parts, hit=False)
    result.complete = False
    return result
