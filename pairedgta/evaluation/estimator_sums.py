"""Two label-free estimators of issue 49 as registered metrics (their class here, one line in `registry.METRICS`),
from the same forward pass as xi: the sums they need per image go into group_counts.npz, and
`Estimators.write` scores them with the others (pairedgta/metrics/estimators.py: `nuclear_norm`, `energy`).

* `NuclearNorm`: per image the K x K Gram matrix P^T P of its pixels' softmax matrix P (pixels x classes),
  summed on the device (`predict_maps(gram=True)`): Grams add over images, so a condition's pooled score and
  its bootstrap need no probabilities on the host.
* `Energy`: per image the sum over pixels of logsumexp of the logits (the negative free energy at T = 1;
  `predict_maps(energy=True)`). A family whose output is already a distribution (Mask2Former) has no logits:
  its sums are NaN, and estimators.csv says so (`has_logits`)."""
from __future__ import annotations

from typing import Any

import numpy as np

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.evaluation import reductions
from pairedgta.evaluation.metric import Group, GroupContext, Metric, per_condition


def _nan(groups: list[dict[str, Any]], conditions: list[str], *shape: int) -> np.ndarray:
    return np.full((len(groups), len(conditions), *shape), np.nan)


class NuclearNorm(Metric):
    """Per image the Gram matrix P^T P of the softmax matrix (Deng et al., ICML 2023)."""

    name, version, needs = "nuclear_norm", "1", ("gram",)

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        return {} if ctx.gram is None else {"gram": ctx.gram}

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, Any]:
        gram = host.get("gram")
        return {c: None if gram is None else gram[i].tolist() for i, c in enumerate(group.conditions)}

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """`est_gram[g, i]`: K x K, NaN where the model gave none."""
        gram = _nan(groups, conditions, NUM_CLASSES, NUM_CLASSES)
        for g, i, m in per_condition(groups, self.name, conditions):
            if m is not None:
                gram[g, i] = m
        return {"est_gram": gram}


class Energy(Metric):
    """Per image the sum over pixels of logsumexp of the logits (Liu et al., NeurIPS 2020's negative energy)."""

    name, version, needs = "energy", "1", ("energy",)

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        return {} if ctx.energy is None else {"energy_blocks": reductions.block_sums(ctx.energy)}

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, Any]:
        blocks = host.get("energy_blocks")
        return {c: None if blocks is None else reductions.ordered_sum(blocks[i]) for i, c in enumerate(group.conditions)}

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """`est_energy_sum[g, i]`, NaN where the model has no logits."""
        energy = _nan(groups, conditions)
        for g, i, v in per_condition(groups, self.name, conditions):
            if v is not None:
                energy[g, i] = v
        return {"est_energy_sum": energy}


__all__ = ["NuclearNorm", "Energy"]
