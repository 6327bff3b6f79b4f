"""Every model a run uses comes from the composed config through one channel, from the CLI as a user runs it:
`model.<key>=` reaches the model wherever it is used, `model_overrides.<name>.<key>=` any other model, and
a sweep over `model=` evaluates exactly the swept model per job."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from pairedgta import schema
from pairedgta.errors import ConfigError
from pairedgta.stages.planning import model_group_overridden, run_models
from pairedgta.testing.cli import base_overrides, compose_cfg, run_cli


def tiny_smoke(tmp: Path) -> list[str]:
    """The smoke experiment (models=[tiny_segformer, tiny_mask2former], reference tiny_segformer), smaller."""
    return ["+experiment=smoke", *base_overrides(tmp), "generate.num_scenes=2", "renderer.width=64",
            "renderer.height=32", "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]", "tracking.enabled=false",
            "stages=[generate,pseudolabel,evaluate]", "metric.bootstrap.resamples=20"]


def manifests(cache: Path, stage: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((cache / stage).glob("[!.]*/manifest.json"))]


def evaluated(cache: Path) -> dict[str, dict]:
    return {m["config"]["model"]["name"]: m["config"]["model"] for m in manifests(cache, "evaluate")}


@pytest.mark.slow
def test_model_key_reaches_the_model_as_subject_and_as_reference(tmp_path):
    proc = run_cli(tiny_smoke(tmp_path) + ["model.init_seed=7", "model_overrides.tiny_mask2former.init_seed=3"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cache = tmp_path / "cache"
    models = evaluated(cache)
    assert set(models) == {"tiny_segformer", "tiny_mask2former"}  # the experiment's list, model= not chosen
    assert models["tiny_segformer"]["init_seed"] == 7
    assert models["tiny_mask2former"]["init_seed"] == 3
    (pseudo,) = manifests(cache, "pseudolabel")
    assert pseudo["config"]["reference_model"]["name"] == "tiny_segformer"
    assert pseudo["config"]["reference_model"]["init_seed"] == 7  # the reference is the same model


@pytest.mark.slow
def test_override_of_a_model_the_run_does_not_use_is_one_line(tmp_path):
    proc = run_cli(tiny_smoke(tmp_path) + ["model_overrides.segformer_b5.path=/weights/b5"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "model_overrides.segformer_b5" in errors[0] and "not used by this run" in errors[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "cache" / "generate").exists()  # refused before anything ran


@pytest.mark.slow
def test_unknown_model_key_is_one_line(tmp_path):
    proc = run_cli(tiny_smoke(tmp_path) + ["+model.widht=3"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "error: model (tiny_segformer): unknown key(s) widht" in proc.stderr


@pytest.mark.slow
def test_sweep_over_model_evaluates_exactly_the_swept_model(tmp_path):
    proc = run_cli(tiny_smoke(tmp_path) + ["model=tiny_segformer,tiny_mask2former"], tmp_path, multirun=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = sorted((tmp_path / "multirun").glob("[0-9]*"))
    assert len(jobs) == 2
    evaluated_per_job = [line.split("[")[1].split("]")[0] for line in proc.stdout.splitlines()
                         if line.strip().startswith("evaluate [")]
    assert sorted(evaluated_per_job) == ["tiny_mask2former", "tiny_segformer"]  # one model per job, no repeats
    assert set(evaluated(tmp_path / "cache")) == {"tiny_segformer", "tiny_mask2former"}
    # the reference stays the experiment's reference_model in both jobs: one pseudo-label entry
    assert len(manifests(tmp_path / "cache", "pseudolabel")) == 1


def test_model_path_override_under_an_experiment_with_a_models_list():
    """The first bug of the issue: `model.path=` under paper_table must reach segformer_b5 (evaluated
    and reference); nothing is loaded here, the composed configs are checked."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_container(compose_cfg(["+experiment=paper_table", "model.path=/weights/b5"]), resolve=True)
    models = run_models(schema.parse(cfg))
    b5 = next(m for m in models.evaluated if m["name"] == "segformer_b5")
    assert b5["path"] == "/weights/b5" and models.reference["path"] == "/weights/b5"
    others = [m for m in models.evaluated if m["name"] != "segformer_b5"]
    assert len(others) == 7 and all(m.get("path") is None for m in others)
    swept = run_models(schema.parse(cfg), model_chosen=True)
    assert [m["name"] for m in swept.evaluated] == ["segformer_b5"]


@pytest.mark.parametrize("overrides,chosen", [(["model=x"], True), (["+model=x"], True), (["model.path=/w"], False),
                                              (["models=[a]"], False), ([], False)])
def test_model_choice_is_read_from_the_command_line(overrides, chosen):
    assert model_group_overridden(overrides) is chosen


def test_model_overrides_must_be_mappings():
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_container(compose_cfg(["+experiment=smoke"]), resolve=True)
    cfg["model_overrides"] = {"tiny_mask2former": 3}
    with pytest.raises(ConfigError, match="model_overrides.tiny_mask2former must be a mapping"):
        run_models(schema.parse(cfg))


def test_an_evaluation_gives_back_a_buildable_model_config(tmp_path):
    """Local weights enter the hash as a content fingerprint; the config read back must still build."""
    from pairedgta.models import check_model_config, model_config
    from pairedgta.stages.common import model_hash_config
    from pairedgta.evaluation.work import EvaluateResult

    hashed = model_hash_config(model_config("demo_segformer"))
    assert "weights_sha256" in hashed
    (tmp_path / "manifest.json").write_text(json.dumps({"config": {"model": hashed}}))
    cfg = EvaluateResult("evaluate", "k", tmp_path, hit=True).model_config()
    check_model_config(cfg)
    assert cfg["path"] == model_config("demo_segformer")["path"]


@pytest.mark.slow
def test_a_sweep_of_models_is_drawn_together_by_collect_cached(tmp_path):
    """`-m model=a,b` evaluates one model per job; a plot run with plot.collect_cached then draws every
    cached evaluation of the same dataset and pseudo-labels in one models x conditions heatmap."""
    sweep = run_cli(tiny_smoke(tmp_path) + ["model=tiny_segformer,tiny_ddrnet"], tmp_path, multirun=True)
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    args = [a for a in tiny_smoke(tmp_path) if not a.startswith("stages=")]
    plot = run_cli(args + ["models=null", "stages=[plot]", "plot.collect_cached=true", "plot.figures=[xi_models]"],
                   tmp_path)
    assert plot.returncode == 0, plot.stderr[-3000:]
    where = Path(plot.stdout.split("results: ")[1].split()[0])
    import pandas as pd

    table = pd.read_csv(where / "xi_models.csv")
    assert set(table["model"]) == {"tiny_segformer", "tiny_ddrnet"} and set(table["condition"]) == {"Night-EXTRASUNNY"}
    assert (where / "xi_models.png").is_file()
