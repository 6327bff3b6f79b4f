"""Is a model set up right? Its clean ground-truth mIoU on a few labelled clean images of the dataset, under the
configured input contract and label space and under each likely alternative, and the one-line diagnosis.

A researcher's model (a model source, pairedgta/models/contract.py) runs under a contract the user spells out
(channel order, scale, mean/std) and a label space; one wrong key and every number after it measures the mistake,
not the model. A model whose clean mIoU is below `SETUP_MIN_MIOU` is tried, on the same few images and with the one
network already loaded (only the contract and the label map around it change), with each alternative a user would
type as one change (`model.channels=bgr`, `model.scale=255 ...`, `model.mean=... model.std=...`,
`model.labels=...`). An alternative that clearly does better names the likely cause; when none does, the model does
not recognise the images at all: a domain gap, not a robustness result.

mIoU follows the Cityscapes convention (`pairedgta.metrics.ConfusionMatrix`: classes with TP + FP + FN > 0), as the
evaluate stage's gt_iou. The evaluate stage (first evaluation of a source model) stores the configured row, plus the
alternatives when the configured mIoU is low, in `SETUP_CSV` and the summary keys below; the model_check stage
(`+experiment=model_check`) writes the whole table. Torch is imported only to run the model."""
from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import PairedDataset, load_image, load_label
from pairedgta.errors import DataError, ModelError
from pairedgta.jsonio import write_json
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD, torch_threads

log = logging.getLogger("pairedgta.setup_check")

SETUP_MIN_MIOU = 0.10   # below it, the model is not measured but mis-set-up or out of its domain
CLEARLY_BETTER = (2.0, 0.05)  # an alternative names the cause when it is >= 2x and >= +0.05 the configured mIoU
CHECK_IMAGES = 4        # labelled clean images the check runs on (groups spread over the dataset)
CONFIGURED = "configured"  # the `setup` of the configured row
SETUP_CSV = "setup_check.csv"
SUMMARY_KEYS = ("clean_miou_check", "setup_warning")  # what an evaluate entry's summary.json gains
VERSION = "1"
VERSION_TAG = f"+setup_check@{VERSION}"  # joins the evaluate stage's version for a model source's entry only
DOCS = "docs/models.md"
ADVICE = ("evaluate it on GTA V frames (renderer=deepgtav) or your own paired data "
          "(dataset=paired_gta dataset.root=...)")
# mean/std sets tried, in 0-1 units (scaled by the configured scale)
NORMALISATIONS = {"ImageNet": (IMAGENET_MEAN, IMAGENET_STD), "0.5": ((0.5,) * 3, (0.5,) * 3),
                  "none": ((0.0,) * 3, (1.0,) * 3)}


@dataclass(frozen=True)
class Setup:
    """One row of the check: the configured set-up (`change` = CONFIGURED) or one alternative, as typed."""

    change: str
    contract: Any  # pairedgta.models.contract.Contract, or None for a model outside the contract (a zoo model)
    labels: Any    # pairedgta.models.labels.LabelMap, or None


@dataclass(frozen=True)
class Row:
    change: str
    miou: float
    iou: tuple[float, ...]  # per Cityscapes class; NaN where neither the truth nor the prediction has it
    n_images: int
    error: str | None = None  # the alternative's forward failed (e.g. not finite): its mIoU is NaN


# -- the images ---------------------------------------------------------------------------------------------
def clean_samples(dataset: PairedDataset, n: int = CHECK_IMAGES) -> list[tuple[np.ndarray, np.ndarray]]:
    """Up to `n` (clean image, train-id label) pairs: the reference condition of groups that label it, spread evenly
    over the dataset's groups. Empty when the dataset labels no clean image."""
    ref = dataset.reference
    labelled = [g for g in dataset.groups if ref in g.images and ref in g.labels]
    picked = [labelled[i * len(labelled) // n] for i in range(n)] if len(labelled) > n else labelled
    out = []
    for g in picked:
        image, label = load_image(g.images[ref]), load_label(g.labels[ref])
        if image.shape[:2] != label.shape:
            raise DataError(f"{g.labels[ref]}: label map size differs from its image")
        out.append((image, label))
    return out


# -- the alternatives ---------------------------------------------------------------------------------------
def _numbers(values: Sequence[float]) -> str:
    return "[" + ",".join(f"{v:.6g}" for v in values) + "]"


def _normalisation(mean: Sequence[float], std: Sequence[float]) -> str:
    return f"model.mean={_numbers(mean)} model.std={_numbers(std)}"


def _effect(contract: Any, labels: Any) -> tuple:
    """What a set-up does to a pixel: x -> x * scale / std - mean / std per channel, after the channel order, and the
    label map. Two set-ups with the same effect are one (scale=255 with mean/std in 0-255 units is scale=1)."""
    affine = tuple(f"{contract.scale / s:.6g}|{m / s:.6g}" for m, s in zip(contract.mean, contract.std))
    return contract.channels, affine, labels.target


def setups(seg: Any) -> list[Setup]:
    """The configured set-up, then each alternative as the change a user would type: the other channel order; each
    usual mean/std (ImageNet, 0.5, none) in the configured scale's units; the other scale with mean/std as they are
    and with each usual mean/std in its units; each shipped label space that fits the output channels. An
    alternative that does what the configured set-up (or an earlier one) does is left out. Only a model under the
    shared contract (a model source) has alternatives; a zoo model's input is the project's own: its one row."""
    from pairedgta.models.contract import ContractSegmenter

    if not isinstance(seg, ContractSegmenter):
        return [Setup(CONFIGURED, None, None)]
    c, labels = seg.contract, seg.labels
    flipped = "bgr" if c.channels == "rgb" else "rgb"
    candidates = [Setup(CONFIGURED, c, labels), Setup(f"model.channels={flipped}", replace(c, channels=flipped), labels)]
    other = 255.0 if c.scale == 1 else 1.0

    def normalised(scale: float, prefix: str) -> list[Setup]:
        out = []
        for name, (m0, s0) in NORMALISATIONS.items():
            mean = tuple(m * scale for m in m0)
            std = s0 if name == "none" else tuple(s * scale for s in s0)
            out.append(Setup(f"{prefix}{_normalisation(mean, std)}", replace(c, scale=scale, mean=mean, std=std),
                             labels))
        return out

    candidates += normalised(c.scale, "")
    candidates.append(Setup(f"model.scale={other:g}", replace(c, scale=other), labels))  # mean/std as they are
    candidates += normalised(other, f"model.scale={other:g} ")
    candidates += [Setup(f"model.labels={space}", c, alt) for space, alt in label_alternatives(seg)]
    out, seen = [], set()
    for s in candidates:
        effect = _effect(s.contract, s.labels)
        if effect not in seen:
            seen.add(effect)
            out.append(s)
    return out


def label_alternatives(seg: Any) -> list[tuple[str, Any]]:
    """Each shipped label space, other than the configured one, whose table fits the model's output channels."""
    from pairedgta.models.labels import SHIPPED, fit_outputs, resolve_labels

    channels, out = seg.labels.num_outputs, []
    for space in SHIPPED:
        if space == seg.labels.space:
            continue
        try:
            alt = fit_outputs(resolve_labels(space, id2label=seg.network.id2label), channels, seg.name)
        except Exception:  # ModelError / ConfigError: the space does not fit this model's outputs
            continue
        if alt.target != seg.labels.target:
            out.append((space, alt))
    return out


def variant(seg: Any, setup: Setup) -> Any:
    """`seg` with another contract and label map around the same loaded network (no reload, no recompile)."""
    if setup.contract is None or (setup.contract is seg.contract and setup.labels is seg.labels):
        return seg
    import torch

    v = copy.copy(seg)
    v.contract, v.labels, v._nonfinite = setup.contract, setup.labels, None
    v._mean = torch.tensor(setup.contract.mean, dtype=torch.float32, device=seg.device).view(1, 3, 1, 1)
    v._std = torch.tensor(setup.contract.std, dtype=torch.float32, device=seg.device).view(1, 3, 1, 1)
    return v


# -- scoring ------------------------------------------------------------------------------------------------
def score(seg: Any, samples: Sequence[tuple[np.ndarray, np.ndarray]], change: str = CONFIGURED) -> Row:
    """Clean mIoU and per-class IoU of `seg` over `samples`, one image per forward."""
    import torch

    from pairedgta.metrics import ConfusionMatrix

    cm = ConfusionMatrix(NUM_CLASSES, IGNORE_INDEX)
    try:
        for image, label in samples:
            pred, _ = seg.predict(image[None])
            cm.update(torch.from_numpy(label.astype(np.int64)), pred[0])
    except ModelError as exc:
        if change == CONFIGURED:
            raise
        return Row(change, math.nan, (math.nan,) * NUM_CLASSES, len(samples), str(exc))
    iou = cm.iou().numpy().astype(float)
    labels = getattr(seg, "labels", None)  # a model source: the classes its label space cannot predict are NaN,
    blind = [CLASS_NAMES.index(c) for c in getattr(labels, "unpredictable", ())]  # not 0, as in gt_iou.csv
    iou[blind] = math.nan
    miou = float(np.nanmean(iou)) if np.isfinite(iou).any() else math.nan
    return Row(change, miou, tuple(float(v) for v in iou), len(samples))


def check(seg: Any, samples: Sequence[tuple[np.ndarray, np.ndarray]], alternatives: bool = True) -> list[Row]:
    """The configured row, then (with `alternatives`) one per alternative set-up."""
    todo = setups(seg) if alternatives else setups(seg)[:1]
    return [score(variant(seg, s), samples, s.change) for s in todo]


def needs_alternatives(configured: Row) -> bool:
    return not math.isnan(configured.miou) and configured.miou < SETUP_MIN_MIOU


def run_check(seg: Any, samples: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[Row]:
    """The evaluate stage's check: the configured row; the alternatives only when it is below SETUP_MIN_MIOU
    (where the diagnosis needs them), so a model set up right pays for a few forwards only."""
    rows = check(seg, samples, alternatives=False)
    if needs_alternatives(rows[0]) and len(setups(seg)) > 1:
        rows += [score(variant(seg, s), samples, s.change) for s in setups(seg)[1:]]
    return rows


# -- the diagnosis ------------------------------------------------------------------------------------------
def best_alternative(rows: Sequence[Row]) -> Row | None:
    scored = [r for r in rows[1:] if not math.isnan(r.miou)]
    return max(scored, key=lambda r: r.miou) if scored else None


def diagnose(model: str, rows: Sequence[Row], where: str = "the embedded town") -> str | None:
    """The one warning line for a configured clean mIoU below SETUP_MIN_MIOU, else None: the alternative that
    clearly does better, or (none does) the domain gap."""
    configured = rows[0]
    if not needs_alternatives(configured):
        return None
    head = f"{model}: clean GT mIoU {configured.miou:.2f} on {where} ({configured.n_images} labelled clean images)"
    best = best_alternative(rows)
    ratio, margin = CLEARLY_BETTER
    if (best is not None and best.miou >= SETUP_MIN_MIOU and best.miou >= ratio * configured.miou
            and best.miou >= configured.miou + margin):
        return f"{head}; with {best.change} it would be {best.miou:.2f}: check the model's input contract ({DOCS})"
    tried = ("no other channel order, scale, mean/std or label space does better" if len(rows) > 1 else
             "a zoo model's input is the project's own")
    return (f"{head}, and {tried}: the model does not recognise {where} (a domain gap, not a robustness result); "
            f"its xi under the conditions says little: {ADVICE}")


def place(cfg: dict[str, Any], dataset_key: str, dataset_name: str) -> str:
    """How a line names the images: the embedded town (a generated dataset of the project's own renderers), else
    the dataset."""
    backend = (cfg.get("renderer") or {}).get("backend")
    if str(dataset_key).startswith("generate:") and backend != "deepgtav":
        return "the embedded town"
    return f"the {dataset_name} images"


# -- the table ----------------------------------------------------------------------------------------------
def table(rows: Sequence[Row]) -> Any:
    """One row per set-up: `setup` (CONFIGURED or the change), clean_miou, n_images, then IoU per class."""
    import pandas as pd

    records = [{"setup": r.change, "clean_miou": r.miou, "n_images": r.n_images,
                **{name: r.iou[k] for k, name in enumerate(CLASS_NAMES)}, "error": r.error or ""} for r in rows]
    return pd.DataFrame(records, columns=["setup", "clean_miou", "n_images", *CLASS_NAMES, "error"])


def markdown(df: Any) -> str:
    """The table for a terminal or a README: the classes some row saw (an all-NaN column says nothing), 2 decimals."""
    seen = [c for c in CLASS_NAMES if df[c].notna().any()]
    head = ["set-up", "clean mIoU", *seen]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]

    def fmt(v: Any) -> str:
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"

    for values in df.to_dict("records"):
        setup = "as configured" if values["setup"] == CONFIGURED else f"`{values['setup']}`"
        lines.append("| " + " | ".join([setup, fmt(values["clean_miou"]), *(fmt(values[c]) for c in seen)]) + " |")
    return "\n".join(lines)


def read_table(path: Path) -> Any:
    import pandas as pd

    return pd.read_csv(path, keep_default_na=False, na_values=[""]).fillna({"error": ""})


# -- the evaluate entry -------------------------------------------------------------------------------------
def store(out: Path, model: str, seg: Any, dataset: PairedDataset, where: str,
          summary: dict[str, Any] | None = None, threads: int | None = None) -> dict[str, Any]:
    """The check of an evaluate entry being built in `out`: SETUP_CSV and the SUMMARY_KEYS added to its summary.json
    (and to `summary`, the dict the stage returns). No labelled clean image: the keys are null, no table."""
    from pairedgta.evaluation import entry

    samples = clean_samples(dataset)
    keys: dict[str, Any] = dict.fromkeys(SUMMARY_KEYS)
    if samples:
        with torch_threads(threads):
            rows = run_check(seg, samples)
        table(rows).to_csv(out / SETUP_CSV, index=False)
        keys = {"clean_miou_check": rows[0].miou, "setup_warning": diagnose(model, rows, where)}
    else:
        log.info("setup check [%s]: %s labels no clean (%s) image; not checked", model, dataset.name, dataset.reference)
    stored = entry.read_summary(out)
    stored.update(keys)
    write_json(out / entry.SUMMARY, stored)
    if summary is not None:
        summary.update(keys)
    return keys


def report(path: Path) -> str | None:
    """The stored warning of an evaluate entry (computed now or cached), logged as one WARNING line."""
    from pairedgta.evaluation import entry

    warning = entry.read_summary(path).get("setup_warning")
    if warning:
        log.warning("%s", warning)
    return warning


__all__ = ["SETUP_MIN_MIOU", "CHECK_IMAGES", "SETUP_CSV", "SUMMARY_KEYS", "Setup", "Row", "clean_samples", "setups",
           "check", "run_check", "diagnose", "place", "table", "markdown", "read_table", "store", "report"]
