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


def _cli(tmp: Path, cache: str, *extra: str) -> subprocess.CompletedProcess:
    over = [a for a in fast_overrides(tmp) if not a.startswith(("cache_dir=", "model=", "reference_model="))]
    args = [*over, "task=presence", f"hydra.searchpath=[file://{PLUGIN / 'conf'}]", f"cache_dir={tmp / cache}",
            "model=tiny_ddrnet", "reference_model=tiny_segformer", f"hydra.run.dir={tmp / 'run'}", *extra]
    env = {**os.environ, **OFFLINE, "PYTHONPATH": os.pathsep.join([str(PLUGIN), str(ROOT)])}
    r = subprocess.run([sys.executable, str(PLUGIN / "run.py"), *args], cwd=tmp, capture_output=True, text=True,
                       env=env, timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    return r


def _entry(tmp: Path, cache: str) -> Path:
    (entry,) = [p for p in (tmp / cache / "evaluate").iterdir() if not p.name.startswith(".")]
    return entry


@pytest.mark.slow
def test_a_toy_task_runs_through_the_cli_with_cache_shards_and_mlflow(tmp_path):
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
