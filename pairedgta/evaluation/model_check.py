"""Segmentation's model check (the work of the `model_check` stage for task=segmentation): is a model set up right?
Its clean ground-truth mIoU and per-class IoU on a few labelled clean images of the run's dataset, under the configured
input contract and label space and under each alternative (pairedgta/evaluation/setup_check.py), kept as CSV and
markdown with the one-line diagnosis: the alternative that clearly beats the configured set-up
(pairedgta/evaluation/alternatives.py's rule), or the domain gap. A zoo model gets its configured row only: its input
is the project's own, the alternatives are a model source's contract keys."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from pairedgta.datasets import PairedDataset
from pairedgta.entries import Context, StageResult, model_hash_config
from pairedgta.errors import DataError
from pairedgta.evaluation import alternatives, setup_check
from pairedgta.jsonio import write_json
from pairedgta.models import shared_model
from pairedgta.work import Work

log = logging.getLogger("pairedgta.model_check")
STAGE = "model_check"
VERSION = "2"  # 2: `better` and `rule` in summary.json (the trial of pairedgta/evaluation/alternatives.py)
TABLE_CSV, TABLE_MD, SUMMARY = "model_check.csv", "model_check.md", "summary.json"


class ModelCheckResult(StageResult):
    """One model's check entry and the readers of its files."""

    def table(self) -> Any:
        return setup_check.read_table(self.path / TABLE_CSV)

    def markdown(self) -> str:
        return (self.path / TABLE_MD).read_text()

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / SUMMARY).read_text())

    def artifacts(self) -> list[Path]:
        return [self.path / f for f in (TABLE_CSV, TABLE_MD, SUMMARY)]


def compute(ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any], out: Path) -> dict[str, Any]:
    model = str(model_cfg["name"])
    samples = setup_check.clean_samples(dataset)
    if not samples:
        raise DataError(f"{STAGE}: dataset {dataset.name} labels no clean ({dataset.reference}) image; the check needs "
                        "ground truth (the embedded town's renderers write it: leave dataset.root unset)")
    segmenter = shared_model(model_cfg, device=ctx.run.device)
    rows = setup_check.check(segmenter, samples)
    where = setup_check.place(ctx.cfg, dataset_key, dataset.name)
    df = setup_check.table(rows)
    df.to_csv(out / TABLE_CSV, index=False)
    md = setup_check.markdown(df)
    warning = setup_check.diagnose(model, rows, where)
    best = setup_check.best_alternative(rows)
    (out / TABLE_MD).write_text(f"# {STAGE}: {model} on {where}\n\n{md}\n\n{warning or 'Set up right: no warning.'}\n")
    ratio, margin = setup_check.CLEARLY_BETTER
    summary = {"model": model, "dataset": dataset.name, "where": where, "condition": dataset.reference,
               "n_images": len(samples), "clean_miou": rows[0].miou,
               "threshold": setup_check.SETUP_MIN_MIOU, "rule": {"ratio": ratio, "margin": margin},
               "best_alternative": None if best is None else {"setup": best.change, "clean_miou": best.miou},
               "better": setup_check.better_record(rows), "alternatives": len(rows) - 1, "warning": warning}
    write_json(out / SUMMARY, summary)
    return summary


@dataclass(frozen=True)
class SegmentationModelCheck(Work):
    """The `model_check` stage's work for segmentation (pairedgta.work.CheckWork)."""

    ENTRY_VERSION: ClassVar[str] = VERSION
    result_cls: type[ModelCheckResult] = ModelCheckResult

    def hash_config(self, ctx: Context, dataset: PairedDataset, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return {"model": model_hash_config(model_cfg), "images": setup_check.CHECK_IMAGES,
                "threshold": setup_check.SETUP_MIN_MIOU, "rule": list(setup_check.CLEARLY_BETTER),
                "check": setup_check.VERSION, "threads": ctx.run.threads}

    def compute(self, ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any],
                out: Path) -> dict[str, Any]:
        return compute(ctx, dataset, dataset_key, model_cfg, out)

    def files(self, result: StageResult) -> list[Path]:
        return [result.path / f for f in (TABLE_CSV, TABLE_MD, SUMMARY)]

    def report(self, result: StageResult, model_cfg: dict[str, Any]) -> tuple[dict[str, float], dict[str, Any]]:
        s = json.loads((result.path / SUMMARY).read_text())
        table = setup_check.markdown(setup_check.read_table(result.path / TABLE_CSV))
        return alternatives.report(STAGE, model_cfg["name"], s, "clean_miou", "clean GT mIoU",
                                   setup_check.SETUP_MIN_MIOU, table, result.path / TABLE_CSV)

__all__ = ["ModelCheckResult", "SegmentationModelCheck", "TABLE_CSV", "TABLE_MD", "compute"]
