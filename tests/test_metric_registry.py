"""One declaration per metric (issue 50): a metric is its class and one line in `registry.METRICS`; the device
reductions, the per-group records, the entry's tables, its files, its readers and the evaluate stage's version
all follow from that list."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pairedgta.evaluation import registry
from pairedgta.evaluation.metric import Metric, per_condition

TOY = "toy_road.csv"


class ToyRoad(Metric):
    """Touch 1 of 2: per condition, the pixels predicted as road (class 0), pooled over the groups."""

    name, version, files = "toy_road", "1", (TOY,)

    def update(self, ctx):
        return {"road": (ctx.labels == 0).sum((1, 2))}

    def record(self, host, group):
        return {c: int(host["road"][i]) for i, c in enumerate(group.conditions)}

    def write(self, out, e, summary, arrays):
        totals = dict.fromkeys(e.conditions, 0)
        for _, i, n in per_condition(e.groups, self.name, e.conditions):
            totals[e.conditions[i]] += n
        pd.DataFrame({"condition": list(totals), "road_pixels": list(totals.values())}).to_csv(out / TOY, index=False)


def _entry(tmp: Path):
    """The evaluate entry of the tiny offline pipeline (synthetic renderer, random-init tiny model): its folder."""
    from pairedgta.app import run
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    summary = run(compose_cfg(fast_overrides(tmp) + ["stages=[generate,pseudolabel,evaluate]"]))
    path, = summary["evaluate"].values()
    return Path(path)


def _digests(path: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.iterdir()) if p.is_file()
            and p.name != "manifest.json"}


def _declared(*decl: str) -> list[Metric]:
    return [type("Declared", (Metric,), {"name": d.split("@")[0], "version": d.split("@")[1]})() for d in decl]


def test_the_stage_version_is_derived_from_the_registered_metrics():
    """The metrics of VERSION 8 keep the bare VERSION (making them a registry moved no cached entry); any other
    list appends its declaration: one without a metric, and today's (issue 49's estimators registered since)."""
    assert registry.stage_version("8", _declared(*registry.VERSION_8_METRICS)) == "8"
    assert registry.stage_version("8", _declared(*registry.VERSION_8_METRICS[:-1])) != "8"
    assert registry.stage_version("8") == "8+" + ",".join(registry.declaration()) != "8"
    assert registry.stage_version("8", [*registry.METRICS, ToyRoad()]) == "8+" + ",".join(
        [*registry.declaration(), "toy_road@1"])


@pytest.mark.slow
def test_a_toy_metric_in_two_touches(tmp_path, monkeypatch):
    """Registered with one line, the toy metric is reduced on the device, written, listed, read back, and
    moves the stage's key; every other file of the entry stays byte for byte what it was."""
    from pairedgta.evaluation.work import EvaluateResult

    before = _entry(tmp_path)
    monkeypatch.setattr(registry, "METRICS", [*registry.METRICS, ToyRoad()])  # touch 2 of 2
    after = _entry(tmp_path)
    assert after.name != before.name and after.parent == before.parent  # a new cache key, no hand bump
    old, new = _digests(before), _digests(after)
    assert set(new) - set(old) == {TOY} and {k: new[k] for k in old} == old
    result = EvaluateResult("evaluate", after.name, after, hit=True)
    assert TOY in result.FILES and after / TOY in result.artifacts()
    table = result.read(TOY)
    with np.load(after / "predictions.npz") as z:  # the label maps of the same forward pass, counted here
        conditions = [str(c) for c in z["conditions"]]
        road = sum((z[k] == 0).sum(axis=(1, 2)) for k in z.files if k[1:].isdigit())
    assert table["condition"].tolist() == conditions and table["road_pixels"].tolist() == road.tolist()
    assert not (before / TOY).exists()
