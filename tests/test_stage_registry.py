"""A stage is its module and one line in pairedgta/stage_registry.py: a toy stage added so runs through the real
app and the cache, and the schema, the plan, the pass and the plot's inputs see it with no other edit."""
from __future__ import annotations

import dataclasses
import json
import textwrap

import pytest

from pairedgta import schema, stage_registry
from pairedgta.errors import ConfigError

# The toy stage's whole module: per group, the pixels its pseudo-label keeps, as one json.
TOY_MODULE = '''
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pairedgta.jsonio import write_json
from pairedgta.stages.common import Context, StageResult, Unsharded, run_cached


@dataclass
class Toy(Unsharded):
    ctx: Context
    pseudo: Any
    name: str = "toy"
    version: str = "1"
    label: str = ""
    resumable: bool = False
    result_cls: type = StageResult

    def hash_config(self) -> dict:
        return {}

    def inputs(self) -> dict:
        return {"pseudolabel": self.pseudo.key}

    def build(self, out: Path, key: str) -> dict:
        write_json(out / "kept.json", {r.group_id: int(r.valid_pixels) for r in self.pseudo.index().itertuples()})
        return {}


def step(ctx: Context, p: "PassResult", state: "RunState") -> None:
    p.kept = run_cached(ctx, Toy(ctx, p.pseudo))
'''
TOY = stage_registry.StageSpec("toy", "toy_stage", "Toy", needs=("pseudolabel",), slot="kept")


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """The toy module on the path and its one registry line, after pseudolabel."""
    (tmp_path / "toy_stage.py").write_text(textwrap.dedent(TOY_MODULE))
    monkeypatch.syspath_prepend(str(tmp_path))
    specs = list(stage_registry.STAGES)
    specs.insert([s.name for s in specs].index("pseudolabel") + 1, TOY)
    monkeypatch.setattr(stage_registry, "STAGES", tuple(specs))
    return TOY


def test_the_schema_plan_and_pass_see_a_registered_stage(toy):
    from pairedgta.stages import planning

    assert schema.STAGES[:3] == ("generate", "pseudolabel", "toy")
    schema.parse({"stages": ["generate", "toy"], "force": ["toy"]})  # a known stage now
    plan = planning.Plan(["toy"], set(), set())
    assert [s.name for s in plan.steps("dataset", "pass")] == ["generate", "pseudolabel", "toy"]  # and what it needs
    assert not plan.runs("evaluate")
    p = planning.PassResult("a", {}, None)  # type: ignore[arg-type]
    assert p.kept is None and "kept" in p.results
    p.kept = "result"
    assert p.results["kept"] == "result"


def test_the_plot_key_includes_a_registered_stage(toy):
    """The plot's inputs are every slot of each pass: the toy's result enters the plot key with no edit of plot.py."""
    from types import SimpleNamespace

    from pairedgta.stages import planning, plot

    ctx = SimpleNamespace(cfg={"plot": {"figures": []}}, run=schema.parse({}))
    p = planning.PassResult("a", {}, SimpleNamespace(reference="Day-EXTRASUNNY"))  # type: ignore[arg-type]
    p.__dict__["run"] = ctx.run
    p.pseudo, p.kept = SimpleNamespace(key="p1"), SimpleNamespace(key="t1")
    _, inputs = plot.plot_key(ctx, [p])  # type: ignore[arg-type]
    assert inputs == {"0:a/pseudolabel": "p1", "0:a/toy": "t1"}


def test_an_unknown_stage_is_still_refused():
    with pytest.raises(ConfigError, match=r"stages=\['toy'\] names unknown stage\(s\); stages are generate, "):
        schema.parse({"stages": ["toy"]})


def test_a_check_stage_runs_alone_by_its_scope(monkeypatch):
    """The check is recognised by its scope, not by its place in the list."""
    specs = [dataclasses.replace(s, scope="pass") if s.scope == "check" else s for s in stage_registry.STAGES]
    monkeypatch.setattr(stage_registry, "STAGES", (stage_registry.StageSpec("probe", "x", "X", scope="check"), *specs))
    schema.parse({"stages": ["cityscapes_val", "plot"]})
    with pytest.raises(ConfigError, match=r"probe is a model check of its own; run it alone \(stages=\[probe\]\)"):
        schema.parse({"stages": ["probe", "plot"]})


@pytest.mark.slow
def test_a_toy_stage_runs_through_the_cached_graph(toy, tmp_path):
    from pairedgta.app import run
    from pairedgta.evaluation.pseudolabel import PseudoLabels
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    args = fast_overrides(tmp_path) + ["stages=[generate,pseudolabel,toy]"]
    first = run(compose_cfg(args))
    entry, = (s for s in first["stages"] if s["stage"] == "toy")
    assert not entry["hit"]
    kept = json.loads((tmp_path / "cache" / "toy" / entry["key"] / "kept.json").read_text())
    pseudo, = (s for s in first["stages"] if s["stage"] == "pseudolabel")
    index = PseudoLabels("pseudolabel", pseudo["key"], tmp_path / "cache" / "pseudolabel" / pseudo["key"], True).index()
    assert kept == dict(zip(index.group_id, index.valid_pixels.astype(int))) and len(kept) == 3
    again = run(compose_cfg(args))
    assert [(s["stage"], s["hit"]) for s in again["stages"]] == [("generate", True), ("pseudolabel", True),
                                                                    ("toy", True)]
    assert [s["key"] for s in again["stages"] if s["stage"] == "toy"] == [entry["key"]]
