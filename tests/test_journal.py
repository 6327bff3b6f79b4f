"""The record survives a busy store: what a locked, stopped or full store refuses goes to a journal beside
the cache and into the store later (at the end of the run, or when the next run opens it), complete,
with a final status, and nothing written twice, even when a replay is killed half-way."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pairedgta.app import run
from pairedgta.testing.cli import compose_cfg, fast_overrides, locked_sqlite, mlflow_store
from pairedgta.tracking import journal as journals
from pairedgta.tracking import mlflow_tracker
from pairedgta.tracking.mlflow_tracker import Tracker


def _tracked(tmp: Path, uri: str, extra: list[str] = ()) -> list[str]:
    over = [o for o in fast_overrides(tmp) if not o.startswith(("tracking.", "plot.formats"))]
    return over + [f"tracking.uri={uri}", "tracking.enabled=true", "tracking.background=false", "name=jrn",
                   "plot.formats=[png]", "models=[tiny_segformer,tiny_deeplabv3plus]",
                   "plot.figures=[xi_models]", *extra]


_locked = locked_sqlite  # another program holding the sqlite store's write lock


def _record(uri: str, experiment: str = "jrn") -> list[dict]:
    """Every run of the experiment: status, parent, tags, each metric's history length, artifacts."""
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(experiment)
    out = []
    for r in client.search_runs([exp.experiment_id], order_by=["attributes.start_time ASC"]):
        rid = r.info.run_id
        history = {k: len(client.get_metric_history(rid, k)) for k in r.data.metrics}
        arts = {a.path for a in client.list_artifacts(rid)}
        out.append({"id": rid, "status": r.info.status, "parent": r.data.tags.get("mlflow.parentRunId"),
                    "model": r.data.tags.get("model"), "metrics": r.data.metrics, "history": history,
                    "params": r.data.params, "artifacts": arts, "inputs": len(r.inputs.dataset_inputs)})
    return out


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == "pairedgta.tracking"]


MODELS = {"tiny_segformer", "tiny_deeplabv3plus"}


def _check_complete(runs: list[dict], invocations: int, models: set[str] = MODELS) -> None:
    parents = [r for r in runs if r["parent"] is None]
    nested = [r for r in runs if r["parent"] is not None]
    assert len(parents) == invocations, runs
    assert len(nested) == len(models) * invocations and {r["model"] for r in nested} == models
    assert all(r["status"] == "FINISHED" for r in runs), [(r["status"], r["model"]) for r in runs]
    for r in nested:
        assert r["parent"] in {p["id"] for p in parents}
        assert any(k.startswith("xi") for k in r["metrics"]) and r["inputs"] == 1, r
        assert set(r["history"].values()) == {1}, r["history"]  # nothing written twice
    for p in parents:
        assert p["params"] and "config.yaml" in p["artifacts"]


@pytest.mark.slow
def test_a_store_locked_longer_than_the_run_gets_the_whole_record_from_the_next_run(tmp_path, caplog, monkeypatch,
                                                                                   short_waits):
    """The lock lands while the run renders and outlasts it: the run exits normally with its results, says
    where the journal is; the next run against the store (the lock gone) writes the first run's parent
    and nested runs into it, finished, with every metric, parameter, input and artifact, once."""
    from pairedgta.render.synthetic import SyntheticRenderer

    caplog.set_level(logging.INFO, logger="pairedgta.tracking")
    monkeypatch.setattr(mlflow_tracker, "RETRY_DELAYS_S", (0.0, 0.1))
    db = tmp_path / "mlflow.db"
    uri = mlflow_store(db)
    lock = contextlib.ExitStack()
    real = SyntheticRenderer.render

    def render_then_lock(self, descriptor, condition):
        if not lock._exit_callbacks:
            lock.enter_context(_locked(db))
        return real(self, descriptor, condition)

    monkeypatch.setattr(SyntheticRenderer, "render", render_then_lock)
    with lock:
        summary = run(compose_cfg(_tracked(tmp_path, uri)))
    monkeypatch.setattr(SyntheticRenderer, "render", real)
    assert Path(summary["plot"], "xi_models.csv").is_file()
    (failed,) = _warnings(caplog)
    (journal,) = journals.pending(tmp_path / "cache", uri)
    assert "database is locked" in failed and str(journal) in failed and "next run" in failed
    still = [r.getMessage() for r in caplog.records if "still fails at the end of the run" in r.getMessage()]
    assert len(still) == 1 and str(journal) in still[0]
    header, entries, done = journals.read(journal)
    assert header["uri"] == uri and entries and not done
    assert summary["mlflow"] is None  # no link to a store that does not hold the run yet

    caplog.clear()
    Tracker(uri, "jrn", results=tmp_path / "cache")  # the lock is gone: what the next run does as it opens the store
    assert not _warnings(caplog)
    assert not journals.pending(tmp_path / "cache", uri) and not journal.with_suffix(".files").exists()
    _check_complete(_record(uri), invocations=1)


@pytest.mark.slow
def test_through_the_cli_the_tracking_child_journals_a_locked_store_and_the_next_run_replays_it(tmp_path):
    """As a user meets it: `python -m pairedgta` (a fresh interpreter, MLflow in the tracking child) while
    another program holds the store's lock for the whole run: exit 0, the results line, one warning naming
    the journal; then the same command once the lock is gone: both invocations complete in the store."""
    from pairedgta.testing.cli import run_cli

    db = tmp_path / "mlflow.db"
    uri = mlflow_store(db)
    # an in-project tiny model as the model and the reference: the fresh interpreter imports no transformers (3 s)
    args = [a for a in _tracked(tmp_path, uri) if a != "tracking.background=false"
            and not a.startswith(("model=", "reference_model="))] + ["model=tiny_ddrnet", "reference_model=tiny_ddrnet"]
    with _locked(db):
        proc = run_cli(args, tmp_path, subprocess_=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "results: " in proc.stdout and "error:" not in proc.stderr
    (journal,) = journals.pending(tmp_path / "cache", uri)
    said = [line for line in (proc.stdout + proc.stderr).splitlines() if "MLflow store" in line]
    assert len(said) == 2, said  # it failed (the warning), and still fails at the end: each with the journal's path
    assert "failed while opening the experiment" in said[0] and all(str(journal) in line for line in said)
    Tracker(uri, "jrn", results=tmp_path / "cache")  # the lock gone: the next run, as it opens the store
    assert not journals.pending(tmp_path / "cache", uri)
    # `model=` on a command line chooses the one model to evaluate (set above)
    _check_complete(_record(uri), invocations=1, models={"tiny_ddrnet"})


@pytest.mark.slow
def test_a_lock_released_before_the_run_ends_is_replayed_by_the_run_itself(tmp_path, caplog, monkeypatch, short_waits):
    """Locked from the first stage's start to the evaluate stage: the journal goes in at the run's end."""
    from pairedgta.stages import evaluate

    caplog.set_level(logging.INFO, logger="pairedgta.tracking")
    monkeypatch.setattr(mlflow_tracker, "RETRY_DELAYS_S", (0.0,))
    db = tmp_path / "mlflow.db"
    uri = mlflow_store(db)
    lock = contextlib.ExitStack()
    lock.enter_context(_locked(db))
    real = evaluate.step

    def unlock_then_evaluate(*args, **kwargs):
        lock.close()
        return real(*args, **kwargs)

    monkeypatch.setattr(evaluate, "step", unlock_then_evaluate)
    try:
        summary = run(compose_cfg(_tracked(tmp_path, uri)))
    finally:
        lock.close()
    (failed,) = _warnings(caplog)
    assert "failed while opening the experiment" in failed and "database is locked" in failed
    assert any("answers again" in r.getMessage() for r in caplog.records)
    assert not journals.pending(tmp_path / "cache", uri)
    assert summary["mlflow"] is not None
    _check_complete(_record(uri), invocations=1)


@pytest.mark.slow
@pytest.mark.cluster
def test_a_stopped_tracking_server_gets_the_record_once_it_is_back(tmp_path, caplog, short_waits):
    """A server that is down for the whole run (connection refused): the run takes seconds more, not
    MLflow's minutes of retries, and the next run, with the server up, writes the run's record into it."""
    from pairedgta.testing.mlflow_server import Server

    server = Server(tmp_path / "server", backend="sqlite")
    started = time.monotonic()
    summary = run(compose_cfg(_tracked(tmp_path, server.uri)))
    assert time.monotonic() - started < 120
    assert Path(summary["plot"], "xi_models.csv").is_file()
    assert "no tracking server answers" in _warnings(caplog)[0]
    assert len(journals.pending(tmp_path / "cache", server.uri)) == 1
    server.start()
    try:
        caplog.clear()
        Tracker(server.uri, "jrn", results=tmp_path / "cache")  # the next run, as it opens the store
        assert not _warnings(caplog)
        assert not journals.pending(tmp_path / "cache", server.uri)
        _check_complete(_record(server.uri), invocations=1)
    finally:
        server.stop()


# -- the journal alone: replay killed half-way, a full disk ----------------------------------------------
def _journal_with_runs(root: Path, uri: str, metrics: int) -> Path:
    """A tracker whose store refused it from the start: a parent run, a nested run with `metrics` metrics
    (one call each), a table, a text artifact, a dataset; both runs ended. Returns the journal's path."""
    tracker = Tracker(uri, "jrn", results=root)
    assert tracker.to_journal("a test", RuntimeError("refused"))
    import pandas as pd

    with tracker.run("parent"):
        tracker.params({"a": 1, "b": {"c": "x"}})
        with tracker.run("child", nested=True):
            tracker.tags({"model": "m"})
            for i in range(metrics):
                tracker.metrics({f"m{i}": float(i)})
            path = root / "note.txt"
            path.write_text("hello")
            tracker.stage_files("evaluate.abc", False, [path], "evaluate",
                                tables={"xi.json": pd.DataFrame({"x": [1.0, 2.0]})})
            tracker.dataset("data", root, "digest1")
    journal = tracker.journal
    assert journal is not None
    path = journal.path
    journal.close()  # as a run that ended while the store still refused (no replay here)
    tracker.journal = None
    return path


def _check_journal_record(uri: str, metrics: int) -> None:
    runs = _record(uri)
    assert len(runs) == 2 and all(r["status"] == "FINISHED" for r in runs)
    child = next(r for r in runs if r["parent"])
    assert child["metrics"] == {f"m{i}": float(i) for i in range(metrics)}
    assert set(child["history"].values()) == {1} and child["inputs"] == 1
    assert {"evaluate", "xi.json"} <= child["artifacts"]
    from mlflow import MlflowClient

    local = MlflowClient(tracking_uri=uri).download_artifacts(child["id"], "xi.json")
    assert json.loads(Path(local).read_text())["data"] == [[1.0], [2.0]]  # written once, not appended twice


@pytest.mark.slow
def test_a_replay_killed_half_way_is_finished_by_the_next_without_duplicates(tmp_path):
    uri = mlflow_store(tmp_path / "mlflow.db")
    n = 60
    journal = _journal_with_runs(tmp_path, uri, n)
    script = textwrap.dedent(f"""
        import time
        from mlflow import MlflowClient
        real = MlflowClient.log_batch
        def slow(self, *a, **k):
            time.sleep(0.1)
            return real(self, *a, **k)
        MlflowClient.log_batch = slow
        from pairedgta.tracking.mlflow_tracker import Tracker
        Tracker({uri!r}, "jrn", results={str(tmp_path)!r})
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(journals.read(journal)[2]) < 10:
        assert proc.poll() is None, "the replay ended before it could be killed"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    _, entries, done = journals.read(journal)
    assert 10 <= len(done) < len(entries)
    tracker = Tracker(uri, "jrn", results=tmp_path)  # the next run against the store
    assert tracker.journal is None and not journal.exists()
    _check_journal_record(uri, n)


def test_the_journal_is_appended_and_synced_one_entry_per_call(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd)))
    j = journals.Journal(tmp_path, "sqlite:///x.db", "e")
    client = journals.JournalClient(j)
    rid = client.create_run("0", run_name="r", tags={"a": "b"}).info.run_id
    client.set_terminated(rid, "FINISHED")
    lines = j.path.read_text().splitlines()
    assert [json.loads(x).get("op") for x in lines] == [None, "create_run", "set_terminated"]
    assert len(synced) == 3 and rid.startswith(journals.LOCAL_PREFIX)
    # a run that still writes its journal holds its lock: nobody replays it meanwhile
    replay = journals.Replay(client=None, experiment_of=None, log_table=None)
    assert replay.run(j.path) is None
    j.close()


def test_a_journal_that_cannot_be_written_switches_mlflow_off_with_one_warning(tmp_path, caplog):
    (tmp_path / "cache").write_text("not a folder")
    tracker = Tracker("sqlite:///unused.db", "e", enabled=False, results=tmp_path / "cache")
    tracker.enabled = True
    assert tracker.to_journal("testing", RuntimeError("x")) is False
    assert tracker.journal is None
