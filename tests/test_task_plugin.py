"""A third task is one declaration and its work (issue 69): the toy task of tests/task_plugin/ (per-image class
presence, scored against the reference's clean presence and the renderer's labels) is declared outside the package,
in one `Task` entry (tests/task_plugin/run.py) with its option file, and runs through `cli()` with the cache, shard
jobs and the MLflow record, touching nothing in pairedgta/stages, planning, report or figures."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from pairedgta.testing.cli import OFFLINE, fast_overrides, mlflow_store

PLUGIN = Path(__file__).resolve().parent / "task_plugin"
ROOT = PLUGIN.parents[1]


@pytest.fixture
def presence(monkeypatch):
    """The toy task declared as its plug-in does (tests/task_plugin/run.py), for the in-process CLI runs below."""
    from pairedgta import tasks

    monkeypatch.syspath_prepend(str(PLUGIN))
    monkeypatch.setitem(tasks.TASKS, "presence", tasks.Task(
        "presence", "segmenter",
        {"pseudolabel": "presence_task:PresencePseudolabels", "evaluate": "presence_task:PresenceEvaluate"},
        what="class presence", title="mean presence recall", example="model=tiny_segformer"))


def _cli(tmp: Path, cache: str, *extra: str) -> subprocess.CompletedProcess:
    """`cli()` in this process (pairedgta.testing.cli.run_cli) with the toy task's option file on the search path."""
    from pairedgta.testing.cli import run_cli

    over = [a for a in fast_overrides(tmp) if not a.startswith(("cache_dir=", "model=", "reference_model="))]
    args = [*over, "task=presence", f"hydra.searchpath=[file://{PLUGIN / 'conf'}]", f"cache_dir={tmp / cache}",
            "model=tiny_ddrnet", "reference_model=tiny_segformer", *extra]
    r = run_cli(args, tmp)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    return r


def test_the_plugin_script_declares_the_task_and_runs_the_cli(tmp_path):
    """tests/task_plugin/run.py, as a user runs it: the declaration, then the real CLI in a fresh interpreter (a
    configuration error is enough to show the task is known: its option file found, its name a choice)."""
    env = {**os.environ, **OFFLINE, "PYTHONPATH": os.pathsep.join([str(PLUGIN), str(ROOT)])}
    r = subprocess.run([sys.executable, str(PLUGIN / "run.py"), "task=presence",
                        f"hydra.searchpath=[file://{PLUGIN / 'conf'}]", "metric.bootstrap.resamples=-1",
                        f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode != 0 and "metric.bootstrap.resamples" in r.stderr, r.stderr[-2000:]
    assert "task=" not in r.stderr.split("metric.bootstrap.resamples")[0][-200:]  # not a complaint about the task


def _entry(tmp: Path, cache: str) -> Path:
    (entry,) = [p for p in (tmp / cache / "evaluate").iterdir() if not p.name.startswith(".")]
    return entry


@pytest.mark.slow
def test_a_toy_task_runs_through_the_cli_with_cache_shards_and_mlflow(tmp_path, presence):
    uri = mlflow_store(tmp_path / "mlflow.db")
    first = _cli(tmp_path, "a", "tracking.enabled=true", f"tracking.uri={uri}")
    out = first.stdout + first.stderr
    assert "mean presence recall" in out and "tiny_ddrnet" in out, out[-3000:]  # the terminal table, its title
    table = pd.read_csv(_entry(tmp_path, "a") / "presence.csv")
    assert list(table["condition"]) == ["Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY"]
    assert table["xi"].between(0, 1).all() and table["accuracy"].between(0, 1).all()
    summary = json.loads((_entry(tmp_path, "a") / "summary.json").read_text())
    assert summary["task"] == "presence" and summary["reference_model"] == "tiny_segformer" and summary["groups"] == 3

    again = _cli(tmp_path, "a")  # the cache: every stage a hit
    assert "evaluate [tiny_ddrnet]: cache hit" in again.stdout + again.stderr
    assert "pseudolabel [tiny_segformer]: cache hit" in again.stdout + again.stderr

    # shard jobs: each evaluates its groups, the unsharded run merges them into the same entry as one job's
    jobs = ["stages=[generate,pseudolabel,evaluate]", "evaluate.num_shards=2"]
    _cli(tmp_path, "b", *jobs, "evaluate.shard=0")
    assert not [p for p in (tmp_path / "b" / "evaluate").iterdir() if not p.name.startswith(".")]  # parts only
    _cli(tmp_path, "b", *jobs, "evaluate.shard=1")
    _cli(tmp_path, "b", "stages=[evaluate]")
    merged = _entry(tmp_path, "b")
    assert merged.name == _entry(tmp_path, "a").name  # the same key
    assert (merged / "presence.csv").read_bytes() == (_entry(tmp_path, "a") / "presence.csv").read_bytes()
    assert not list((tmp_path / "b" / "evaluate").glob(".parts-*"))  # merged into the entry

    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    nested = [r for r in runs if r.data.tags.get("model") == "tiny_ddrnet"]
    assert nested and nested[0].data.tags["task"] == "presence"
    assert nested[0].data.metrics["presence_recall/Day-RAIN"] == pytest.approx(
        float(table.set_index("condition").loc["Day-RAIN", "xi"]))


def _detector_check(tmp: Path, *model: str) -> subprocess.CompletedProcess:
    from pairedgta.testing.cli import base_overrides, run_cli

    args = ["+experiment=model_check", "task=detection", *base_overrides(tmp, store=False), "renderer=synthetic",
            "region=synthetic_street", "renderer.width=96", "renderer.height=48", "generate.num_scenes=3",
            "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]", "detection.min_area=4", "tracking.enabled=false",
            "threads=1", *model]
    return run_cli(args, tmp)  # in this process: tests/ on sys.path for the factory (the test's monkeypatch)


@pytest.mark.slow
def test_model_check_checks_detectors_as_it_checks_segmenters(tmp_path, monkeypatch):
    """`+experiment=model_check task=detection`: the issue's command ended in an AttributeError ('ContractDetector' has
    no 'predict'); now a researcher's detector gets its clean GT AP50 as configured and under each one-key
    alternative, a zoo detector its configured row, both written to the entry and the run's summary."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent))  # detector_nets, the python factory's module
    proc = _detector_check(tmp_path, "model=python", "model.target=detector_nets:red_car_bgr", "model.labels=coco91")
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert "model_check [red_car_bgr]: clean GT AP50 on" in out and "model.channels=bgr" in out
    (entry,) = [p for p in (tmp_path / "cache" / "model_check").iterdir() if not p.name.startswith(".")]
    table = pd.read_csv(entry / "model_check.csv")
    assert table["setup"].iloc[0] == "configured" and "model.channels=bgr" in set(table["setup"])
    summary = json.loads((entry / "summary.json").read_text())
    assert summary["task"] == "detection" and summary["alternatives"] == len(table) - 1 >= 1
    assert "| set-up | clean GT AP50 | images |" in (entry / "model_check.md").read_text()

    zoo = _detector_check(tmp_path, "model=tiny_fcos")
    assert zoo.returncode == 0, zoo.stderr[-3000:]
    assert "generate: cache hit" in zoo.stdout + zoo.stderr  # the scenes rendered once
    rows = [pd.read_csv(p / "model_check.csv") for p in (tmp_path / "cache" / "model_check").iterdir()
            if not p.name.startswith(".") and p != entry]
    assert len(rows) == 1 and list(rows[0]["setup"]) == ["configured"]


def test_a_detector_key_out_of_range_stops_before_any_stage(tmp_path):
    """The issue's late error: model.score_threshold=2 stopped evaluate after rendering and pseudo-labelling; now the
    run stops with one line before anything is computed (the cache stays empty)."""
    from pairedgta.errors import ConfigError
    from pairedgta.models import check_model_config, model_config

    cfg = model_config("demo_fcos_adverse", score_threshold=2)
    with pytest.raises(ConfigError, match=r"score_threshold=2 must be in \[0, 1\]"):
        check_model_config(cfg)
    for key, value in (("min_size", 8), ("max_size", "big")):
        with pytest.raises(ConfigError, match=key):
            check_model_config(model_config("demo_fcos_adverse", **{key: value}))

    from pairedgta.testing.cli import base_overrides, run_cli

    proc = run_cli(["task=detection", *base_overrides(tmp_path, store=False), "renderer=synthetic",
                    "region=synthetic_street", "model=demo_fcos_adverse", "model.score_threshold=2",
                    "tracking.enabled=false"], tmp_path)
    assert proc.returncode != 0 and "score_threshold=2 must be in [0, 1]" in proc.stderr
    assert not (tmp_path / "cache" / "generate").exists()


def test_both_tasks_metrics_follow_one_protocol():
    """Each task's registered metrics are pairedgta.work.TaskMetric (name, version, files): the evaluate entry's version
    and its tables follow from the same two functions for every task."""
    from pairedgta import tasks, work

    for task in tasks.TASKS.values():
        metrics = task.metric_list()
        assert metrics and all(isinstance(m, work.TaskMetric) for m in metrics), task.name
        files = work.result_files(metrics)
        assert len(files) == len(set(files)) and all(f.endswith((".csv", ".npz", ".json")) for f in files)
        assert all("@" in d for d in work.declaration(metrics))
