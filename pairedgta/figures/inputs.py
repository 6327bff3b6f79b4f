"""What a figure may read of a pass, declared here so that figures import no stage.

The plot stage hands each figure the run's passes (`pairedgta.stages.planning.PassResult`) and their
stage results (`GeneratedData`, `PseudoLabels`, `EvaluateResult`); these Protocols name the part of them
that figures use. A figure that needs more adds it here first (tests/test_figures.py checks the stage
classes still provide every member), and a test can hand a figure any object of this shape."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # pandas and the dataset readers load with the figures, not with the plan
    import numpy as np
    import pandas as pd

    from pairedgta.conditions import ConditionGrid
    from pairedgta.datasets.base import LabelMaps, PairedDataset


class Evaluation(Protocol):
    """One model's evaluate entry: its tables, read through the stage's own readers."""

    @property
    def path(self) -> Path: ...

    @property
    def key(self) -> str: ...

    @property
    def model(self) -> str: ...

    def model_config(self) -> dict[str, Any]: ...

    def xi(self) -> pd.DataFrame: ...

    def rho(self) -> pd.DataFrame: ...

    def frame_counts(self) -> pd.DataFrame: ...

    def agreement(self) -> pd.DataFrame: ...

    def gt_iou(self) -> pd.DataFrame: ...

    def summary(self) -> dict[str, Any]: ...

    def group_counts(self) -> dict[str, np.ndarray]: ...


class PseudoLabels(Protocol):
    """The pass's pseudo-labels: one label map per group and their class histogram."""

    @property
    def labels(self) -> LabelMaps: ...

    def histogram(self) -> pd.DataFrame: ...

    def reference_model(self) -> str: ...


class GeneratedData(Protocol):
    """The generate stage's run records of a generated pass."""

    @property
    def timings_csv(self) -> Path: ...

    def validation(self) -> pd.DataFrame | None: ...


class FigurePass(Protocol):
    """One dataset variant of the run: its label, config, condition grid and stage results (None, or no
    evaluations, where the run did not compute that stage for the pass)."""

    @property
    def label(self) -> str: ...

    @property
    def cfg(self) -> dict[str, Any]: ...

    @property
    def run(self) -> Any: ...  # pairedgta.schema.RunConfig of the pass

    @property
    def grid(self) -> ConditionGrid: ...

    @property
    def dataset(self) -> PairedDataset | None: ...

    @property
    def generate(self) -> GeneratedData | None: ...

    @property
    def pseudo(self) -> PseudoLabels | None: ...

    @property
    def evaluations(self) -> Sequence[Evaluation]: ...

    @property
    def pairing(self) -> dict[str, float]: ...


Passes = Sequence[FigurePass]

__all__ = ["Evaluation", "FigurePass", "GeneratedData", "Passes", "PseudoLabels"]
