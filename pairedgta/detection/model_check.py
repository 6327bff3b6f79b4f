"""Detection's model check (the work of the `model_check` stage for task=detection,
`+experiment=model_check task=detection`): is a detector set up right? Its clean GT AP50 on the labelled clean images
with the most scored objects, as configured and -- for a researcher's detector (a model source) -- under each one-key
alternative of its contract and layout (pairedgta/detection/setup_check.py: channel order, scale, normalisation, box
format, label space), with the one-line diagnosis by segmentation's rule (pairedgta/evaluation/alternatives.py). A zoo
detector gets its configured row only. The ground truth is the renderer's instance masks under the clean condition,
by the same rules as the pseudo-label entry's (docs/detection.md)."""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import pandas as pd

from pairedgta.datasets import PairedDataset, load_group_images
from pairedgta.detection import setup_check
from pairedgta.detection.inputs import image_ids
from pairedgta.detection.pseudolabel import condition_ground_truth
from pairedgta.entries import Context, StageResult, model_hash_config
from pairedgta.errors import DataError
from pairedgta.evaluation import alternatives as alts
from pairedgta.jsonio import write_json
from pairedgta.models import is_source, shared_model
from pairedgta.work import Work

log = logging.getLogger("pairedgta.model_check")
STAGE = "model_check"
VERSION = "det1"
TABLE_CSV, TABLE_MD, SUMMARY = "model_check.csv", "model_check.md", "summary.json"


def markdown(df: pd.DataFrame) -> str:
    lines = ["| set-up | clean GT AP50 | images |", "|---|---:|---:|"]
    for r in df.itertuples():
        score = "failed" if not math.isfinite(r.clean_ap50) else f"{r.clean_ap50:.3f}"
        lines.append(f"| {r.setup} | {score} | {r.n_images} |")
    return "\n".join(lines)


def compute(ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any], out: Path,
            task: str) -> dict[str, Any]:
    from pairedgta.evaluation.setup_check import place

    model, clean = str(model_cfg["name"]), dataset.reference
    found = condition_ground_truth(dataset, clean, ctx.run.detection.min_area, ctx.run.metric.min_transmittance)
    if found is None:
        raise DataError(f"{STAGE}: dataset {dataset.name} has no instance masks or boxes on its clean ({clean}) "
                        "images; the detector check needs ground-truth boxes (the embedded town's renderers write "
                        "them: leave dataset.root unset)")
    coco = found[0]
    ids = image_ids(dataset)
    by_id = {ids[g.group_id]: g for g in dataset.groups}
    chosen = [i for i in setup_check.samples(coco) if i in by_id]
    if not chosen:
        raise DataError(f"{STAGE}: no scored object on the clean ({clean}) images of dataset {dataset.name}; render "
                        "more scenes (generate.num_groups) or check detection.min_area")
    images = {i: load_group_images(by_id[i], [clean])[clean] for i in chosen}
    detector = shared_model(model_cfg, device=ctx.run.device)
    if is_source(model_cfg):  # a researcher's detector: every one-key alternative of its contract
        verdict = setup_check.check(detector, images, coco)
    else:  # a zoo detector's input is the project's own: the configured row only
        verdict = alts.trial([alts.Candidate(alts.CONFIGURED, {})],
                             lambda cands: [setup_check.score(detector, images, coco) for _ in cands])
    where = place(ctx.cfg, dataset_key, dataset.name)
    df = pd.DataFrame([{"setup": o.candidate.change, "clean_ap50": o.score, "n_images": len(images)}
                       for o in verdict.outcomes], columns=["setup", "clean_ap50", "n_images"])
    tmp = out / f".{TABLE_CSV}.tmp"
    df.to_csv(tmp, index=False)
    tmp.replace(out / TABLE_CSV)
    warning = setup_check.line(model, verdict, len(images), where)
    (out / TABLE_MD).write_text(f"# {STAGE}: {model} on {where}\n\n{markdown(df)}\n\n"
                                f"{warning or 'Set up right: no warning.'}\n")
    configured = verdict.configured.score
    best = max(verdict.alternatives, key=lambda o: o.score if math.isfinite(o.score) else -1.0, default=None)
    summary = {"task": task, "model": model, "dataset": dataset.name, "where": where, "condition": clean,
               "n_images": len(images), "clean_ap50": None if math.isnan(configured) else configured,
               "threshold": setup_check.MIN_AP50, "rule": {"ratio": alts.RATIO, "margin": alts.MARGIN},
               "best_alternative": None if best is None or not math.isfinite(best.score) else
               {"setup": best.candidate.change, "clean_ap50": best.score},
               "better": alts.record(verdict.better, "clean_ap50"), "alternatives": len(verdict.alternatives),
               "warning": warning}
    write_json(out / SUMMARY, summary)
    return {"clean_ap50": summary["clean_ap50"]}


@dataclass(frozen=True)
class DetectionModelCheck(Work):
    """The `model_check` stage's work for detection (pairedgta.work.CheckWork)."""

    ENTRY_VERSION: ClassVar[str] = VERSION
    result_cls: type[StageResult] = StageResult

    def hash_config(self, ctx: Context, dataset: PairedDataset, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return {"task": self.task.name, "model": model_hash_config(model_cfg), "images": setup_check.CHECK_IMAGES,
                "threshold": setup_check.MIN_AP50, "rule": [alts.RATIO, alts.MARGIN], "threads": ctx.run.threads,
                "ground_truth": {"min_area": ctx.run.detection.min_area,
                                 "min_transmittance": ctx.run.metric.min_transmittance}}

    def compute(self, ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any],
                out: Path) -> dict[str, Any]:
        return compute(ctx, dataset, dataset_key, model_cfg, out, self.task.name)

    def files(self, result: StageResult) -> list[Path]:
        return [result.path / f for f in (TABLE_CSV, TABLE_MD, SUMMARY)]

    def report(self, result: StageResult, model_cfg: dict[str, Any]) -> tuple[dict[str, float], dict[str, Any]]:
        s = json.loads((result.path / SUMMARY).read_text())
        return alts.report(STAGE, model_cfg["name"], s, "clean_ap50", "clean GT AP50", setup_check.MIN_AP50,
                           markdown(pd.read_csv(result.path / TABLE_CSV)), result.path / TABLE_CSV)

__all__ = ["DetectionModelCheck", "compute", "markdown"]
