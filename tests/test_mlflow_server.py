"""The MLflow record against a real tracking server (`mlflow server` on loopback, PostgreSQL behind it
where Debian's postgresql is installed, SQLite otherwise): the default background tracking child logs a
run's whole record, and a sweep of four jobs running at once loses none of their runs."""
from __future__ import annotations

import os
from datetime import datetime
from pathlib import Path

import pytest

from pairedgta.testing.cli import run_cli
from pairedgta.testing.mlflow_server import mlflow_server, postgres_bin

pytestmark = [pytest.mark.cluster, pytest.mark.slow]

SMALL = ["+experiment=smoke", "generate.num_scenes=2", "renderer.width=64", "renderer.height=32",
         "conditions.only=[Day-EXTRASUNNY,Night-RAIN]", "metric.bootstrap.resamples=20",
         "plot.figures=[xi_models]", "plot.formats=[png]", "plot.dpi=50", "threads=1",
         # an in-project tiny model as the model and the reference: the fresh interpreters import no transformers (3 s)
         "models=[tiny_ddrnet]", "reference_model=tiny_ddrnet"]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if postgres_bin() is None and os.environ.get("CI"):
        pytest.fail("CI must test the server on PostgreSQL: .ci/run installs postgresql and psycopg2-binary")
    with mlflow_server(tmp_path_factory.mktemp("mlflow-server")) as srv:
        yield srv


def _log_span(log: Path) -> tuple[datetime, datetime]:
    """The times of a job log's first and last lines (`[2026-11-26 02:51:00,358][pairedgta][INFO] - ...`)."""
    stamps = [datetime.strptime(line[1:24], "%Y-%m-%d %H:%M:%S,%f") for line in log.read_text().splitlines()
              if line.startswith("[")]
    return stamps[0], stamps[-1]


def _records(uri: str, experiment: str):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None, f"no experiment {experiment!r} in the server"
    return client.search_runs([exp.experiment_id], max_results=1000)


def test_four_jobs_at_once_lose_no_run_and_the_background_child_records_a_run(server, tmp_path):
    cache = f"cache_dir={tmp_path / 'cache'}"
    proc = run_cli(SMALL + [cache, f"tracking.uri={server.uri}", "name=sweep4", "stages=[generate]",
                            "hydra/launcher=local", "hydra.launcher.n_jobs=4", "seed=0,1,2,3"],
                   tmp_path, multirun=True, subprocess_=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for log in sorted((tmp_path / "multirun").glob("*/pairedgta.log")):  # e.g. a race on the experiment's tags
        assert "MLflow store" not in log.read_text(), log.read_text()[-3000:]
    runs = _records(server.uri, "sweep4")
    parents = [r for r in runs if not r.data.tags.get("mlflow.parentRunId")]
    # generate-only jobs (no torch to import: the suite's time) each record their run; a run with models
    # nests a run per model, which the run below checks
    assert len(parents) == 4 and len(runs) == 4, [(r.info.run_name, r.info.status) for r in runs]
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert len({r.data.tags.get("pairedgta.sweep") for r in parents}) == 1  # one sweep, told apart by its tag
    # the four jobs ran at once: the last to log its first line did so before the first logged its last.
    # (Their MLflow runs' spans need not overlap: a generate-only job's run is open from when its tracking
    # child has imported MLflow, seconds after the job started, to its end a moment later.)
    spans = sorted(_log_span(log) for log in (tmp_path / "multirun").glob("*/pairedgta.log"))
    assert len(spans) == 4 and max(start for start, _ in spans) < min(end for _, end in spans), spans

    # one run of the whole pipeline (its dataset cached by the sweep) through the default background child: in a
    # fresh interpreter (this one has imported MLflow above, and a run in it would log in-process), and the
    # child's own timing line (hydra.verbose) shows that the child logged it
    proc = run_cli(SMALL + [cache, f"tracking.uri={server.uri}", "name=one_run", "seed=0",
                            "hydra.verbose=pairedgta.tracking"], tmp_path, subprocess_=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    assert "tracking child: MLflow import" in out, out[-2000:]
    assert "stopped before it had logged" not in out and "View run" not in out, out[-2000:]
    runs = _records(server.uri, "one_run")
    parents = [r for r in runs if not r.data.tags.get("mlflow.parentRunId")]
    assert len(parents) == 1 and len(runs) == 2  # the run and its model's nested run
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert all(r.data.metrics for r in runs if r.data.tags.get("mlflow.parentRunId")), "model runs carry metrics"
    assert f"mlflow: {server.uri}/#/experiments/{parents[0].info.experiment_id}" in proc.stdout
