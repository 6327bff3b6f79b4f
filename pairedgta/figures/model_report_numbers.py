"""The numbers of a model report (pairedgta/figures/model_report.py computes them, writes its tables and text) and
their reading, below both that module and its page (pairedgta/figures/model_report_page.py, matplotlib), which
each import them from here."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Report:
    """The numbers of one pass's report; `models[0]` is the subject."""

    subject: str
    reference: str
    population: list[str]              # the members evaluated on this pass, in the listed order
    missing: list[str]                 # listed members without an evaluation here
    clean: str
    conditions: list[str]              # adverse conditions, grid order
    xi: np.ndarray                     # M x C'
    gt: np.ndarray                     # M x C'
    gt_clean: np.ndarray               # M
    n_scenes: int
    scene: dict[str, np.ndarray] | None  # xi, gt, xi_f (M x R x C'), gt_clean (M x R) on scene resamples; None: no counts
    confidence: float
    resamples: int
    seed: int
    # M x C' the F of xi and its precision (evaluate's xi_precision.csv means; NaN where an entry has none): where a
    # model that paints one class everywhere stands once its precision counts, beside its xi rank
    xi_f: np.ndarray | None = None
    rows: list[dict] = field(default_factory=list)      # the subject's standing per (condition, measure)
    track: list[dict] = field(default_factory=list)     # xi vs GT within each condition, and their mean
    worst: list[dict] = field(default_factory=list)     # the conditions where it loses most
    cases: list[dict] = field(default_factory=list)     # its worst (group, condition) images

    @property
    def models(self) -> list[str]:
        return [self.subject, *self.population]

    @property
    def has_gt(self) -> bool:
        return bool(np.isfinite(self.gt[0]).any())


def row(r: Report, condition: str, measure: str) -> dict:
    return next(x for x in r.rows if x["condition"] == condition and x["measure"] == measure)


def rank_text(d: dict) -> str:
    return "–" if not math.isfinite(d["rank"]) else f"{d['rank']:.0f}/{d['n']:.0f}"


def pct_text(d: dict) -> str:
    return "–" if not math.isfinite(d["percentile"]) else f"{d['percentile']:.1f}"


__all__ = ["Report", "row", "rank_text", "pct_text"]
