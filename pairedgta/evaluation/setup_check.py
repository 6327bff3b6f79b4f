"""Is a model set up right? Its clean ground-truth mIoU on a few labelled clean images of the dataset, under the
configured input contract and label space and under each likely alternative, and the one-line diagnosis.

A researcher's model (a model source, pairedgta/models/contract.py) runs under a contract the user spells out
(channel order, scale, mean/std) and a label space; one wrong key and every number after it measures the mistake,
not the model. Every source model is tried, on the same few images and with the one network already loaded (only
the contract and the label map around it change), with each alternative a user would type as one change
(`model.channels=bgr`, `model.scale=255 ...`, `model.mean=... model.std=...`, `model.labels=...`): the trial of
pairedgta/evaluation/alternatives.py, whose rule says when an alternative clearly beats the configured set-up
(>= 1.25x and >= +0.05 clean mIoU). Such an alternative is named in one line, whatever the configured mIoU; below
`SETUP_MIN_MIOU` with none that helps, the model does not recognise the images at all: a domain gap, not a
robustness result. A model set up right says nothing.

The trial is cheap: per image one batch of the distinct contracts' inputs through the network, and the label-space
alternatives re-map the configured output (no forward of their own). mIoU follows the Cityscapes convention
(`pairedgta.metrics.ConfusionMatrix`: classes with TP + FP + FN > 0), as the evaluate stage's gt_iou. The evaluate
stage (first evaluation of a source model) stores the table in `SETUP_CSV` and the summary keys below; the
model_check stage (`+experiment=model_check`) writes it too, with its own summary. Torch is imported only to run
the model."""
from __future__ import annotations

import contextlib
import copy
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import PairedDataset, load_image, load_label
from pairedgta.errors import DataError, ModelError
from pairedgta.evaluation import alternatives as alts
from pairedgta.evaluation.alternatives import CONFIGURED, Candidate
from pairedgta.jsonio import write_json
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD, torch_threads

log = logging.getLogger("pairedgta.setup_check")

SETUP_MIN_MIOU = 0.10   # below it, the model is not measured but mis-set-up or out of its domain
CLEARLY_BETTER = (alts.RATIO, alts.MARGIN)  # the trial's rule: >= 1.25x and >= +0.05 clean mIoU
CHECK_IMAGES = 4        # labelled clean images the check runs on (groups spread over the dataset)
SETUP_CSV = "setup_check.csv"
# what an evaluate entry's summary.json gains: the configured clean mIoU, the warning line, and the alternative it
# names ({"setup": "model.channels=bgr", "overrides": {"channels": "bgr"}, "clean_miou": ...}, else null)
SUMMARY_KEYS = ("clean_miou_check", "setup_warning", "setup_better")
VERSION = "2"  # 2: every source model's alternatives, the 1.25x / +0.05 rule, setup_better
VERSION_TAG = f"+setup_check@{VERSION}"  # joins the evaluate stage's version for a model source's entry only
DOCS = "docs/models.md"
ADVICE = ("evaluate it on GTA V frames (renderer=deepgtav) or your own paired data "
          "(dataset=paired_gta dataset.root=...)")
# mean/std sets tried, in 0-1 units (scaled by the configured scale)
NORMALISATIONS = {"ImageNet": (IMAGENET_MEAN, IMAGENET_STD), "0.5": ((0.5,) * 3, (0.5,) * 3),
                  "none": ((0.0,) * 3, (1.0,) * 3)}


@dataclass(frozen=True)
class Setup(Candidate):
    """One row of the check: the configured set-up (`change` = CONFIGURED) or one alternative, as typed, with the
    model keys it sets (`overrides`) and what it runs."""

    contract: Any = None  # pairedgta.models.contract.Contract, or None for a model outside the contract (a zoo model)
    labels: Any = None    # pairedgta.models.labels.LabelMap, or None


@dataclass(frozen=True)
class Row:
    change: str
    miou: float
    iou: tuple[float, ...]  # per Cityscapes class; NaN where neither the truth nor the prediction has it
    n_images: int
    error: str | None = None  # the alternative's forward failed (e.g. not finite): its mIoU is NaN
    overrides: Mapping[str, Any] = field(default_factory=dict)  # the model keys the set-up sets

    @property
    def score(self) -> float:  # what the trial compares (pairedgta/evaluation/alternatives.py)
        return self.miou


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
        return [Setup(CONFIGURED)]
    c, labels = seg.contract, seg.labels
    flipped = "bgr" if c.channels == "rgb" else "rgb"
    candidates = [Setup(CONFIGURED, {}, c, labels),
                  Setup(f"model.channels={flipped}", {"channels": flipped}, replace(c, channels=flipped), labels)]
    other = 255.0 if c.scale == 1 else 1.0

    def normalised(scale: float, keys: dict[str, Any], prefix: str) -> list[Setup]:
        out = []
        for name, (m0, s0) in NORMALISATIONS.items():
            mean = tuple(float(f"{m * scale:.6g}") for m in m0)
            std = s0 if name == "none" else tuple(float(f"{s * scale:.6g}") for s in s0)
            out.append(Setup(f"{prefix}{_normalisation(mean, std)}", {**keys, "mean": list(mean), "std": list(std)},
                             replace(c, scale=scale, mean=mean, std=std), labels))
        return out

    candidates += normalised(c.scale, {}, "")
    candidates.append(Setup(f"model.scale={other:g}", {"scale": int(other)}, replace(c, scale=other), labels))
    candidates += normalised(other, {"scale": int(other)}, f"model.scale={other:g} ")  # mean/std as they are, above
    candidates += [Setup(f"model.labels={space}", {"labels": space}, c, alt) for space, alt in label_alternatives(seg)]
    out, seen = [], set()
    for s in candidates:
        effect = _effect(s.contract, s.labels)
        if effect not in seen:
            seen.add(effect)
            out.append(s)
    return out


def label_alternatives(seg: Any) -> list[tuple[str, Any]]:
    """Each shipped label space, other than the configured one, whose table fits the model's output channels. Read
    quietly: a space the user never chose says nothing about its names against the checkpoint's."""
    from pairedgta.models.labels import SHIPPED, fit_outputs, resolve_labels

    channels, out = seg.labels.num_outputs, []
    with alts.quiet("pairedgta.models"):
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
def _row(setup: Setup, cm: Any, labels: Any, n: int) -> Row:
    """The row of a confusion matrix: per-class IoU, NaN (not 0, as in gt_iou.csv) for the classes the set-up's
    label space cannot predict; the mean over the rest."""
    iou = cm.iou().numpy().astype(float)
    blind = [CLASS_NAMES.index(c) for c in getattr(labels, "unpredictable", ())]
    iou[blind] = math.nan
    miou = float(np.nanmean(iou)) if np.isfinite(iou).any() else math.nan
    return Row(setup.change, miou, tuple(float(v) for v in iou), n, overrides=dict(setup.overrides))


def _failed(setup: Setup, n: int, error: str) -> Row:
    return Row(setup.change, math.nan, (math.nan,) * NUM_CLASSES, n, error, dict(setup.overrides))


def score(seg: Any, samples: Sequence[tuple[np.ndarray, np.ndarray]], change: str | Setup = CONFIGURED) -> Row:
    """Clean mIoU and per-class IoU of `seg` over `samples`, one image per forward (a zoo model's row, and the
    trial's fallback when its batch fails). A failing alternative is a NaN row with its error; the configured
    set-up's failure raises."""
    import torch

    from pairedgta.metrics import ConfusionMatrix

    setup = change if isinstance(change, Setup) else Setup(change)
    cm = ConfusionMatrix(NUM_CLASSES, IGNORE_INDEX)
    try:
        for image, label in samples:
            pred, _ = seg.predict(image[None])
            cm.update(torch.from_numpy(label.astype(np.int64)), pred[0])
    except ModelError as exc:
        if setup.change == CONFIGURED:
            raise
        return _failed(setup, len(samples), str(exc))
    return _row(setup, cm, getattr(seg, "labels", None), len(samples))


def _batched(seg: Any, todo: Sequence[Setup], samples: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[Row]:
    """Every set-up of `todo` on `samples`: per image, the distinct contracts' preparations in one batch through the
    network (chunks of model.batch_size, under model.amp as a forward is), then each set-up's label map on its
    contract's output. The same numbers as `score` of each variant, with a forward per image and not per set-up."""
    import torch

    from pairedgta.metrics import ConfusionMatrix
    from pairedgta.models.base import max_and_label

    contracts = list(dict.fromkeys(s.contract for s in todo))
    which = [contracts.index(s.contract) for s in todo]
    preparers = [variant(seg, Setup(CONFIGURED, {}, c, seg.labels)) for c in contracts]
    cms = [ConfusionMatrix(NUM_CLASSES, IGNORE_INDEX) for _ in todo]
    errors: list[str | None] = [None] * len(todo)
    amp = (torch.autocast(device_type=seg.device.type, dtype=torch.bfloat16 if seg.amp == "bf16" else torch.float16)
           if seg.amp else contextlib.nullcontext())
    with torch.inference_mode():
        for image, label in samples:
            x = seg.to_device(image[None])
            size = tuple(x.shape[-2:])
            truth = torch.from_numpy(label.astype(np.int64))
            with amp:
                batch = torch.cat([p.prepare(x) for p in preparers])
                dist = torch.cat([seg.distribution(seg.scores_prepared(chunk, size))
                                  for chunk in batch.split(seg.batch_size)])
                maps = [max_and_label(s.labels.apply(dist[k:k + 1]).float()) for s, k in zip(todo, which)]
            for i, (conf, pred) in enumerate(maps):
                if errors[i] is None and not bool(torch.isfinite(conf).all()):
                    errors[i] = (f"{seg.name}: the model's outputs are not finite (NaN or inf); its weights are "
                                 "broken: re-export or download them again")
                if errors[i] is None:
                    cms[i].update(truth, pred[0].long().cpu())
    if errors[0] is not None:
        raise ModelError(errors[0])
    return [_failed(s, len(samples), e) if e else _row(s, cm, s.labels, len(samples))
            for s, cm, e in zip(todo, cms, errors)]


def score_setups(seg: Any, todo: Sequence[Setup], samples: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[Row]:
    """The trial's score callable: one row per set-up of `todo` (the configured one first), batched for a model
    source; a batch that fails (an alternative the network refuses) is retried one set-up at a time, so that only
    that alternative's row is NaN."""
    from pairedgta.models.contract import ContractSegmenter

    if isinstance(seg, ContractSegmenter) and todo and todo[0].contract is not None:
        try:
            return _batched(seg, todo, samples)
        except Exception as exc:  # noqa: BLE001 - retried below, where each set-up's own error is kept
            log.debug("setup check [%s]: batched trial failed (%s); one set-up at a time", seg.name, exc)
    return [score(variant(seg, s), samples, s) for s in todo]


def check(seg: Any, samples: Sequence[tuple[np.ndarray, np.ndarray]], alternatives: bool = True) -> list[Row]:
    """The configured row, then (with `alternatives`) one per alternative set-up: the trial's rows."""
    todo = setups(seg) if alternatives else setups(seg)[:1]
    result = alts.trial(todo, lambda candidates: score_setups(seg, candidates, samples))
    return [o.row for o in result.outcomes]


# -- the diagnosis ------------------------------------------------------------------------------------------
def verdict(rows: Sequence[Row]) -> alts.Verdict:
    """The rows (the configured first) as the trial's verdict."""
    outcomes = [alts.Outcome(Candidate(r.change, dict(r.overrides)), r.miou, r) for r in rows]
    return alts.Verdict(outcomes[0], tuple(outcomes[1:]))


def best_alternative(rows: Sequence[Row]) -> Row | None:
    best = verdict(rows).best
    return None if best is None else best.row


def named(rows: Sequence[Row]) -> Row | None:
    """The alternative the diagnosis names: the best one when it clearly beats the configured set-up (the trial's
    rule) and, for a configured mIoU below SETUP_MIN_MIOU, reaches that line (else the line is the domain gap)."""
    better = verdict(rows).better
    if better is None or (rows[0].miou < SETUP_MIN_MIOU and better.score < SETUP_MIN_MIOU):
        return None
    return better.row


def better_record(rows: Sequence[Row]) -> dict[str, Any] | None:
    """The named alternative as summary.json keeps it: {"setup", "overrides", "clean_miou"}, else None."""
    row = named(rows)
    return None if row is None else {"setup": row.change, "overrides": dict(row.overrides), "clean_miou": row.miou}


def diagnose(model: str, rows: Sequence[Row], where: str = "the embedded town") -> str | None:
    """The one warning line, else None (a model set up right): the alternative that clearly beats the configured
    set-up, at any configured mIoU; below SETUP_MIN_MIOU with none that helps, the domain gap."""
    configured = rows[0]
    if math.isnan(configured.miou):
        return None
    head = f"{model}: clean GT mIoU {configured.miou:.2f} on {where} ({configured.n_images} labelled clean images)"
    better = named(rows)
    if better is not None:
        return f"{head}; with {better.change} it would be {better.miou:.2f}: check the model's input contract ({DOCS})"
    if configured.miou >= SETUP_MIN_MIOU:
        return None
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
            rows = check(seg, samples)
        table(rows).to_csv(out / SETUP_CSV, index=False)
        keys = {"clean_miou_check": rows[0].miou, "setup_warning": diagnose(model, rows, where),
                "setup_better": better_record(rows)}
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


__all__ = ["SETUP_MIN_MIOU", "CLEARLY_BETTER", "CHECK_IMAGES", "SETUP_CSV", "SUMMARY_KEYS", "Setup", "Row",
           "clean_samples", "setups", "score_setups", "check", "verdict", "named", "better_record", "diagnose", "place",
           "table", "markdown", "read_table", "store", "report"]
