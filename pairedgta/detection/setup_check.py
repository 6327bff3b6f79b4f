"""The set-up check for a researcher's detector (task=detection model=<source>): its clean GT AP50 on a few labelled
clean images as configured, and under each alternative a user could type as one change: channel order, input scale,
normalisation (for a network that takes a prepared tensor), the layout's box format and normalisation, and the label
space. The rule and the trial are segmentation's (pairedgta/evaluation/alternatives.py: an alternative clearly beats
the configured set-up at >= 1.25 x and >= +0.05); the line that names it is printed on every run and kept in the
evaluate entry's summary.json (`setup_better`, `setup_clean_ap50`). Below 0.05 with no alternative that helps, the
detector does not recognise the town (a domain gap), and its detection xi says little."""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Sequence

import numpy as np

from pairedgta.evaluation import alternatives as alts
from pairedgta.evaluation.alternatives import CONFIGURED, Candidate

log = logging.getLogger("pairedgta.evaluate")
CHECK_IMAGES = 8  # labelled clean images, the ones with the most scored objects first
MIN_AP50 = 0.05  # below it, with no alternative that helps: the domain gap line
DOCS = "docs/models.md, 'Detectors'"
IMAGENET = ([0.485, 0.456, 0.406], [0.229, 0.224, 0.225])


def candidates(det: Any) -> list[Candidate]:
    """The configured set-up first, then each one-key alternative of this detector's contract."""
    from pairedgta.models import detector_labels as label_spaces
    from pairedgta.models.detector_layouts import BOX_FORMATS

    c = det.contract
    out = [Candidate(CONFIGURED, {})]
    other = "rgb" if c.channels == "bgr" else "bgr"
    out.append(Candidate(f"model.channels={other}", {"channels": other}))
    if not det.network.takes_list:
        scale = 1 if c.scale == 255 else 255
        out.append(Candidate(f"model.scale={scale}", {"scale": scale}))
        plain = list(c.mean) == [0.0, 0.0, 0.0] and list(c.std) == [1.0, 1.0, 1.0]
        mean, std = IMAGENET if plain else ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
        units = 255.0 if c.scale == 255 else 1.0
        mean, std = [m * units for m in mean], [s * units for s in std]
        out.append(Candidate(f"model.mean={mean} model.std={std}", {"mean": mean, "std": std}))
    if c.layout.kind == "tensors":
        for fmt in BOX_FORMATS:
            if fmt != c.layout.box_format:
                out.append(Candidate(f"model.layout.box_format={fmt}", {"layout": {"box_format": fmt}}))
        flip = not c.layout.normalized
        out.append(Candidate(f"model.layout.normalized={str(flip).lower()}", {"layout": {"normalized": flip}}))
    for space, names in label_spaces.SPACES.items():
        if space != det.labels.space and len(names) == det.labels.num_classes:
            out.append(Candidate(f"model.labels={space}", {"labels": space}))
    return out


def variant(det: Any, overrides: dict[str, Any]) -> Any:
    """The same network under the contract with `overrides` (no reload)."""
    from pairedgta.models import detector_labels as label_spaces
    from pairedgta.models.detector_contract import ContractDetector

    if not overrides:
        return det
    contract = det.contract
    keys = {k: v for k, v in overrides.items() if k in ("channels", "scale")}
    if "mean" in overrides:
        keys["mean"], keys["std"] = tuple(overrides["mean"]), tuple(overrides["std"])
    if "scale" in keys:
        keys["scale"] = float(keys["scale"])
    if "layout" in overrides:
        keys["layout"] = dataclasses.replace(contract.layout, name=contract.layout.name + "*", **overrides["layout"])
    labels = label_spaces.resolve(overrides["labels"], None, det.where) if "labels" in overrides else det.labels
    return ContractDetector(det.name, det.network, dataclasses.replace(contract, **keys), labels, det.runtime,
                            det.source)


def samples(coco: dict[str, Any], n: int = CHECK_IMAGES) -> list[int]:
    """The COCO image ids with the most scored objects (ties by id): the few images the trial runs on."""
    scored: dict[int, int] = {}
    for a in coco["annotations"]:
        if not a.get("iscrowd"):
            scored[a["image_id"]] = scored.get(a["image_id"], 0) + 1
    return sorted(scored, key=lambda i: (-scored[i], i))[:n]


def score(det: Any, images: dict[int, np.ndarray], coco: dict[str, Any]) -> float:
    """Clean GT AP50 of `det` on `images` (COCO id -> uint8 image) against `coco` restricted to them."""
    from pairedgta.metrics.coco_ap import average_precision, results_format

    ids = set(images)
    gt = {"images": [im for im in coco["images"] if im["id"] in ids], "categories": coco["categories"],
          "annotations": [a for a in coco["annotations"] if a["image_id"] in ids]}
    results = []
    for iid, image in images.items():
        (d,) = det.detect(image[None])
        results += results_format(iid, d.boxes, d.scores, d.labels + 1)
    from pairedgta.detection.boxes import INSTANCE_CLASSES

    blind = getattr(det, "blind", ())  # a zoo detector predicts every class
    cats = [k + 1 for k, n in enumerate(INSTANCE_CLASSES) if n not in blind]
    return float(average_precision(gt, results, categories=cats)["ap50"])


def check(det: Any, images: dict[int, np.ndarray], coco: dict[str, Any]) -> alts.Verdict:
    """The trial: every candidate scored on the same images; a candidate whose forward fails scores NaN."""
    from pairedgta.errors import PairedGTAError

    def scores(cands: Sequence[Candidate]) -> list[float]:
        out = []
        for cand in cands:
            try:
                with alts.quiet("pairedgta.detection", "pairedgta.models"):
                    out.append(score(variant(det, dict(cand.overrides)), images, coco))
            except (PairedGTAError, ValueError, RuntimeError) as exc:
                if cand.change == CONFIGURED:
                    raise
                log.debug("set-up %s: %s", cand.change, exc)
                out.append(math.nan)
        return out

    return alts.trial(candidates(det), scores)


def line(model: str, verdict: alts.Verdict, n_images: int, where: str) -> str | None:
    configured = verdict.configured.score
    if math.isnan(configured):
        return None
    head = f"{model}: clean GT AP50 {configured:.2f} on {where} ({n_images} labelled clean images)"
    better = verdict.better
    if better is not None:
        return (f"{head}; with {better.candidate.change} it would be {better.score:.2f}: check the detector's input "
                f"contract and output layout ({DOCS})")
    if configured >= MIN_AP50:
        return None
    return (f"{head}, and no other channel order, scale, normalisation, box format or label space does better: the "
            f"detector does not recognise {where} (a domain gap, not a robustness result); its detection xi says "
            "little")


def run(det: Any, dataset: Any, coco: dict[str, Any] | None, clean: str, where: str) -> dict[str, Any]:
    """The check of a source detector on the clean images of `dataset` (their COCO ground truth `coco`): the
    summary.json entries, the line included (None: set up right)."""
    from pairedgta.datasets import load_group_images
    from pairedgta.detection.inputs import image_ids

    if coco is None:
        return {"setup_check": "skipped: no ground truth on the clean images"}
    ids = image_ids(dataset)
    by_id = {i: g for g, i in ((g, ids[g.group_id]) for g in dataset.groups)}
    chosen = [i for i in samples(coco) if i in by_id]
    if not chosen:
        return {"setup_check": "skipped: no scored object on the clean images"}
    images = {i: load_group_images(by_id[i], [clean])[clean] for i in chosen}
    verdict = check(det, images, coco)
    return {"setup_clean_ap50": verdict.configured.score, "setup_better": alts.record(verdict.better, "clean_ap50"),
            "setup_tried": {o.candidate.change: None if math.isnan(o.score) else o.score for o in verdict.outcomes},
            "setup_line": line(det.name, verdict, len(images), where)}


__all__ = ["CHECK_IMAGES", "MIN_AP50", "candidates", "check", "line", "run", "samples", "score", "variant"]
