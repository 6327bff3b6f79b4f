"""The MLflow record: runs that say what ran on what, artifacts next to the database, per-model runs
that carry their own table, figures, dataset and config, and cache-hit reruns that link instead of
uploading the same files again. Disabled tracking touches nothing."""
from __future__ import annotations

import contextlib
import inspect
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from pairedgta.app import run
from pairedgta.testing.cli import compose_cfg, fast_overrides, locked_sqlite, mlflow_store
from pairedgta.tracking import bundle, dataset_label, run_name
from pairedgta.tracking.store import artifact_location

SEP = " \u00b7 "


def _tracked(tmp: Path, db: Path, extra: list[str] = ()) -> list[str]:
    over = [o for o in fast_overrides(tmp) if not o.startswith(("tracking.", "plot.formats"))]
    return over + [f"tracking.uri={mlflow_store(db)}", "tracking.enabled=true", "name=trk", "plot.formats=[png]",
                   "models=[tiny_segformer,tiny_deeplabv3plus]", "plot.figures=[xi_models,xi_table,qualitative,ranking]",
                   "plot.qualitative_groups=1", *extra]


def _artifacts(client, run_id: str, path: str = "") -> set[str]:
    out = set()
    for a in client.list_artifacts(run_id, path or None):
        out |= _artifacts(client, run_id, a.path) if a.is_dir else {a.path}
    return out


def _runs(client, exp_id: str):
    runs = client.search_runs([exp_id], order_by=["attributes.start_time ASC"])
    parents = [r for r in runs if not r.data.tags.get("mlflow.parentRunId")]
    nested = [r for r in runs if r.data.tags.get("mlflow.parentRunId")]
    return parents, nested


@pytest.mark.slow
def test_runs_tables_figures_datasets_and_cache_hit_reruns(tmp_path, monkeypatch):
    import mlflow

    monkeypatch.chdir(tmp_path)  # anything written to ./mlruns would land here
    db = tmp_path / "store" / "mlflow.db"
    first = run(compose_cfg(_tracked(tmp_path, db)))
    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{db}")
    exp = client.get_experiment_by_name("trk")
    assert exp.artifact_location == (db.parent / "mlartifacts" / "trk").as_uri()
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"  # the UI opens on the runs
    assert not (tmp_path / "mlruns").exists()

    gen_key = next(p.name for p in (tmp_path / "cache" / "generate").iterdir() if not p.name.startswith("."))
    data = f"generated@{gen_key[:8]}"
    (parent,), nested = _runs(client, exp.experiment_id)
    assert parent.info.run_name == SEP.join(["trk", "tiny_segformer, tiny_deeplabv3plus", data])
    by_model = {r.data.tags["model"]: r for r in nested}
    assert set(by_model) == {"tiny_segformer", "tiny_deeplabv3plus"}
    plot_dir = Path(first["plot"])
    owners = json.loads((plot_dir / "owners.json").read_text())
    for model, r in by_model.items():
        assert r.info.run_name == SEP.join(["trk", model, data])
        arts = _artifacts(client, r.info.run_id)
        assert {"evaluate/xi.csv", "xi_table.json", "config.yaml", f"figures/xi_table_{model}.png",
                f"figures/qualitative_{model}.png"} <= arts
        other = next(m for m in by_model if m != model)
        assert not any(other in a for a in arts)  # only its own figures
        assert {Path(a).name for a in arts if a.startswith("figures/")} == {n for n, o in owners.items() if o["model"] == model}
        # the xi table as MLflow lines it up: exactly the evaluate stage's numbers
        table = mlflow.load_table("xi_table.json", run_ids=[r.info.run_id])
        xi = pd.read_csv(Path(first["evaluate"][model]) / "xi.csv")
        assert list(table.columns[:7]) == ["model", "reference", "condition", "class", "xi", "ci_low", "ci_high"]
        assert len(table) == len(xi) and set(table["model"]) == {model}
        pd.testing.assert_series_equal(table["xi"].astype(float), xi["xi"].astype(float), check_names=False)
        # the dataset it read, with the generate hash as digest
        (inp,) = r.inputs.dataset_inputs
        assert inp.dataset.name == "generated" and inp.dataset.digest == gen_key
        assert str(tmp_path / "cache" / "generate" / gen_key) in inp.dataset.source
        config = yaml.safe_load(Path(mlflow.artifacts.download_artifacts(f"{r.info.artifact_uri}/config.yaml",
                                                                          dst_path=str(tmp_path / "dl" / model))).read_text())
        assert config["model"]["name"] == model and config["metric"]["bootstrap"]["resamples"] == 50
        # the means and the headline rho per class; per-class xi only with tracking.class_metrics (below)
        prefixes = {k.split("/")[0] + "/*" * k.count("/") for k in r.data.metrics}
        assert {"xi_mean/*", "xi_gt_mean/*", "gt_miou/*", "agreement/*", "estimator/*/*"} == prefixes - {"rho_valid/*/*"}, prefixes
        assert 0 < r.data.metrics["estimator/ac/Day-RAIN"] <= 1  # the label-free estimators beside xi
        assert r.data.metrics["xi_mean/Day-RAIN"] == pytest.approx(
            xi[(xi.condition == "Day-RAIN") & (xi.class_name == "mean") & (xi.reference_model != "ground_truth")].xi.item())
    # the parent carries each model's numbers with the model in the key: one chart compares them
    # (but the reference's xi: it grades its own pseudo-labels and is not compared; its GT mIoU is)
    assert {f"compare/xi_mean/Day-RAIN/{m}" for m in by_model if m != "tiny_segformer"} <= set(parent.data.metrics)
    assert "compare/xi_mean/Day-RAIN/tiny_segformer" not in parent.data.metrics
    assert "compare/gt_miou/Day-RAIN/tiny_segformer" in parent.data.metrics
    assert parent.data.metrics["compare/xi_mean/Day-RAIN/tiny_deeplabv3plus"] == pytest.approx(
        by_model["tiny_deeplabv3plus"].data.metrics["xi_mean/Day-RAIN"])
    parent_arts = _artifacts(client, parent.info.run_id)
    assert {"figures/ranking.png", "figures/table1_xi.csv", "pseudolabel/histogram.csv", "config.yaml"} <= parent_arts
    assert not any(a.startswith("figures/") and a.split("/")[1] in owners for a in parent_arts)
    first_files = sorted(p.relative_to(db.parent) for p in (db.parent / "mlartifacts").rglob("*") if p.is_file())

    # a rerun is a cache hit everywhere: it links the runs that hold the files and uploads none of them
    run(compose_cfg(_tracked(tmp_path, db)))
    parents, nested2 = _runs(client, exp.experiment_id)
    assert len(parents) == 2 and len(nested2) == 4
    again = parents[1]
    assert again.info.run_name == parent.info.run_name
    assert again.data.tags["pairedgta.reused_run"] == parent.info.run_id
    assert parent.info.run_id in again.data.tags["pairedgta.reused_link"]
    assert parent.info.run_id in again.data.tags["mlflow.note.content"]
    assert _artifacts(client, again.info.run_id) == {"config.yaml"}
    for r in nested2[2:]:
        earlier = by_model[r.data.tags["model"]]
        assert r.data.tags["pairedgta.reused_run"] == earlier.info.run_id
        assert _artifacts(client, r.info.run_id) == {"config.yaml"}
        assert r.data.metrics == earlier.data.metrics  # the numbers stay comparable
        assert r.inputs.dataset_inputs[0].dataset.digest == gen_key
    new_files = sorted(p.relative_to(db.parent) for p in (db.parent / "mlartifacts").rglob("*") if p.is_file())
    assert len(new_files) == len(first_files) + 3  # three config.yaml, nothing else

    # recomputed figures (force) are new files: uploaded again; per-class metrics asked for are logged
    run(compose_cfg(_tracked(tmp_path, db, ["force=[plot]", "tracking.class_metrics=true"])))
    parents, nested3 = _runs(client, exp.experiment_id)
    for r in nested3[4:]:
        model = r.data.tags["model"]
        assert {k: v for k, v in r.data.metrics.items() if k in by_model[model].data.metrics} == by_model[model].data.metrics
        xi = pd.read_csv(Path(first["evaluate"][model]) / "xi.csv")
        per_class = xi[(xi.class_name != "mean") & (xi.reference_model != "ground_truth") & xi.xi.notna()]
        assert len(per_class) > 10
        for row in per_class.itertuples():
            assert r.data.metrics[f"xi/{row.condition}/{row.class_name}"] == pytest.approx(row.xi)
        assert any(k.startswith("xi_gt/") for k in r.data.metrics)
    assert "figures/ranking.png" in _artifacts(client, parents[2].info.run_id)
    assert "pairedgta.reused.plot." + Path(first["plot"]).name not in parents[2].data.tags
    assert all(any(a.startswith("figures/") for a in _artifacts(client, r.info.run_id)) for r in nested3[4:])
    assert all("evaluate/xi.csv" not in _artifacts(client, r.info.run_id) for r in nested3[4:])  # evaluate was a hit


def test_disabled_tracking_imports_and_writes_nothing(tmp_path):
    code = (
        "import sys; from pathlib import Path; from pairedgta.tracking.mlflow_tracker import Tracker\n"
        "t = Tracker('sqlite:///' + sys.argv[1] + '/db/mlflow.db', 'x', enabled=False)\n"
        "with t.run('r'):\n"
        "    t.params({'a': 1}); t.metrics({'m': 1.0}); t.config({'a': 1}); t.hydra_config()\n"
        "    t.dataset('d', '/nowhere', 'abc'); assert t.stage_files('evaluate.k', True, [Path(sys.argv[0])]) is None\n"
        "print('mlflow' in sys.modules)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "False"
    assert list(tmp_path.iterdir()) == []


def test_names_locations_and_bundles():
    assert run_name("smoke", ["a", "b"], ["generated@1234abcd"]) == "smoke \u00b7 a, b \u00b7 generated@1234abcd"
    assert dataset_label("generated", "generate:1234abcd5678") == "generated@1234abcd"
    assert dataset_label("acdc", None) == "acdc"
    assert artifact_location("sqlite:////data/runs/mlflow.db", "paper table") == "file:///data/runs/mlartifacts/paper_table"
    assert artifact_location("http://127.0.0.1:5000", "x") is None  # a server keeps its own
    assert bundle("plot", "abc", "night vs/acdc", "segformer_b5") == "plot.abc.night_vs_acdc.segformer_b5"



def _signature(fn) -> list[tuple]:
    return [(p.name, p.kind, p.default, p.annotation) for p in inspect.signature(fn).parameters.values()]


def test_both_recorders_have_every_member_of_the_interface_with_its_signature():
    """`Recorder` is what the app and the stages may call; the in-process Tracker and the BackgroundTracker
    proxy each define every member with the same parameters (names, kinds, defaults, annotations), so a
    method added to one cannot be forgotten on the other."""
    from pairedgta.tracking import Recorder
    from pairedgta.tracking.background import BackgroundTracker
    from pairedgta.tracking.mlflow_tracker import Tracker

    methods = {n: f for n, f in vars(Recorder).items() if inspect.isfunction(f) and not n.startswith("_")}
    assert {"run", "run_id", "rename", "params", "metrics", "tags", "stage_files", "dataset", "config",
            "hydra_config", "ui_link", "close"} == set(methods)
    assert set(Recorder.__annotations__) == {"experiment"}
    for cls in (Tracker, BackgroundTracker):
        for name, declared in methods.items():
            assert name in vars(cls), f"{cls.__name__}.{name} is missing (not inherited, not forwarded)"
            assert _signature(getattr(cls, name)) == _signature(declared), f"{cls.__name__}.{name}"
    assert isinstance(Tracker("sqlite:///never/written.db", "x", enabled=False), Recorder)  # data members too


def test_the_child_replays_every_call_the_proxy_sends():
    """Each Recorder method of the proxy is one message, and the child's table of calls (FORWARDED) is
    exactly those messages, each a method of the Tracker it replays them on."""
    from pairedgta.tracking import Recorder
    from pairedgta.tracking.background import BackgroundTracker
    from pairedgta.tracking.child import FORWARDED
    from pairedgta.tracking.mlflow_tracker import Tracker

    sent: list[str] = []
    proxy = object.__new__(BackgroundTracker)  # no child process: only what it would send
    proxy._stack, proxy._handles, proxy._summary = [], 0, None
    proxy._send = lambda method, *args, **kwargs: sent.append(method)
    local = {"run", "run_id", "ui_link", "close"}  # run: begin/finish below; the others answer in this process
    for name, declared in vars(Recorder).items():
        if inspect.isfunction(declared) and not name.startswith("_") and name not in local:
            required = [p for p in list(inspect.signature(declared).parameters.values())[1:] if p.default is p.empty]
            getattr(proxy, name)(*[None] * len(required))
    with proxy.run("r"):
        assert proxy.run_id() == "run1"
    assert sent[-2:] == ["begin", "finish"] and len(sent) == len(set(sent))
    assert set(sent[:-2]) == FORWARDED
    assert all(callable(getattr(Tracker, m, None)) for m in FORWARDED)

@pytest.mark.slow
@pytest.mark.parametrize("uri", ["sqlite:///{tmp}/a/mlflow.db", "sqlite:///{tmp}/b/other.db"])
def test_a_user_given_store_gets_the_artifacts_next_to_it(tmp_path, monkeypatch, uri):
    import mlflow

    from pairedgta.tracking.mlflow_tracker import Tracker

    monkeypatch.chdir(tmp_path)
    uri = uri.format(tmp=tmp_path)
    t = Tracker(uri, "exp")
    with t.run("r"):
        t.config({"k": 1})
    db = Path(uri[len("sqlite:///"):])
    (run_dir,) = [p for p in (db.parent / "mlartifacts" / "exp").iterdir()]
    assert (run_dir / "artifacts" / "config.yaml").is_file()
    assert mlflow.get_experiment_by_name("exp").artifact_location.startswith(db.parent.as_uri())
    assert not (tmp_path / "mlruns").exists()


# --------------------------------------------------------------------------- every run recorded, MLflow not the truth


def _statuses(db: Path) -> list[tuple[str, str]]:
    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{db}")
    exp = client.get_experiment_by_name("trk")
    return [(r.info.status, r.data.tags.get("dataset_key", "")) for r in
            client.search_runs([exp.experiment_id], order_by=["attributes.start_time ASC"])]


@pytest.mark.slow
def test_a_run_that_stops_or_fails_while_generating_is_recorded_with_its_status(tmp_path, monkeypatch):
    """The parent run opens before generation: stages=[generate] ends FINISHED, a failure there (a renderer
    error, a full disk) FAILED, an interrupt KILLED."""
    import errno

    from pairedgta.errors import DiskFullError, RendererError
    from pairedgta.render.synthetic import SyntheticRenderer

    db = tmp_path / "mlflow.db"
    run(compose_cfg(_tracked(tmp_path, db, ["stages=[generate]"])))
    assert _statuses(db) == [("FINISHED", _statuses(db)[0][1])] and _statuses(db)[0][1].startswith("generate:")

    def broken(self, descriptor, condition):
        raise RendererError("the renderer stopped answering")

    monkeypatch.setattr(SyntheticRenderer, "render", broken)
    with pytest.raises(RendererError):
        run(compose_cfg(_tracked(tmp_path, db, ["generate.num_scenes=4"])))
    assert [s for s, _ in _statuses(db)] == ["FINISHED", "FAILED"]

    def disk_full(self, descriptor, condition):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(SyntheticRenderer, "render", disk_full)
    with pytest.raises(DiskFullError):  # a full disk is a failure like any other: FAILED, not KILLED
        run(compose_cfg(_tracked(tmp_path, db, ["generate.num_scenes=6"])))
    assert [s for s, _ in _statuses(db)] == ["FINISHED", "FAILED", "FAILED"]

    def interrupted(self, descriptor, condition):
        raise KeyboardInterrupt

    monkeypatch.setattr(SyntheticRenderer, "render", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(compose_cfg(_tracked(tmp_path, db, ["generate.num_scenes=5"])))
    assert [s for s, _ in _statuses(db)] == ["FINISHED", "FAILED", "FAILED", "KILLED"]


@pytest.mark.slow
def test_a_corrupt_store_costs_the_record_not_the_results(tmp_path, caplog, short_waits):
    db = tmp_path / "mlflow.db"
    db.write_text("not an sqlite database")
    summary = run(compose_cfg(_tracked(tmp_path, db, ["models=[tiny_segformer]", "plot.figures=[xi_models]"])))
    assert Path(summary["plot"], "xi_models.csv").is_file()  # every stage ran and wrote its results
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and r.name == "pairedgta.tracking"]
    assert len(warned) == 1 and "failed while opening the experiment" in warned[0] and "tracking.enabled=false" in warned[0]


@pytest.mark.slow
def test_a_locked_store_is_retried_then_the_run_finishes_without_it(tmp_path, caplog, monkeypatch):
    import sqlite3

    import mlflow

    from pairedgta.tracking import mlflow_tracker

    monkeypatch.setattr(mlflow_tracker, "RETRY_DELAYS_S", (0.0, 0.0, 0.0))
    calls = []

    log_batch = mlflow.MlflowClient.log_batch

    def locked(self, run_id, metrics=(), *args, **kwargs):
        if not metrics:  # params and tags go through
            return log_batch(self, run_id, metrics, *args, **kwargs)
        calls.append(1)
        raise sqlite3.OperationalError("database is locked")

    monkeypatch.setattr(mlflow.MlflowClient, "log_batch", locked)
    db = tmp_path / "mlflow.db"
    summary = run(compose_cfg(_tracked(tmp_path, db, ["models=[tiny_segformer]", "plot.figures=[xi_models]"])))
    assert Path(summary["plot"], "xi_models.csv").is_file()
    # tried, retried three times, then the record goes to the journal; tried once more at the run's end
    assert len(calls) == 5
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and r.name == "pairedgta.tracking"]
    assert len(warned) == 1 and "failed while logging metrics (OperationalError: database is locked)" in warned[0]
    assert "RUNNING" in [s for s, _ in _statuses(db)]  # its end is in the journal, not lost
    monkeypatch.setattr(mlflow.MlflowClient, "log_batch", log_batch)  # the store writes again
    from pairedgta.tracking.mlflow_tracker import Tracker

    Tracker(f"sqlite:///{db}", "trk", results=tmp_path / "cache")  # the next run against the store
    assert {s for s, _ in _statuses(db)} == {"FINISHED"}  # the half-written runs got their record and their end


_locked = locked_sqlite  # another program holding the sqlite store's write lock


@contextlib.contextmanager
def _read_only(path: Path):
    """`path` unwritable even for root (immutable), or by its mode for anyone else; skips where neither works."""
    if os.geteuid() != 0:
        path.chmod(0o444)
        try:
            yield
        finally:
            path.chmod(0o644)
        return
    if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode != 0:
        pytest.skip("running as root where chattr +i is refused: no way to make a read-only file")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(path)], check=True)


def _store_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == "pairedgta.tracking"]


def test_the_shipped_waits_on_a_locked_store_add_up_to_seconds_not_minutes():
    """The runs below meet a locked store with every wait shortened (the `short_waits` fixture); what the
    shipped waits cost a real run is their sum: the probe's wait on each try, the retries within their
    budget, MLflow's busy timeout per statement cut from its 20 s. Below 15 s, where MLflow alone took 80 s
    or more."""
    from pairedgta.tracking import mlflow_tracker, store

    tries = 1 + len(mlflow_tracker.RETRY_DELAYS_S)
    per_call = min(mlflow_tracker.RETRY_BUDGET_S + store.SQLITE_WAIT_S + max(mlflow_tracker.RETRY_DELAYS_S),
                   tries * store.SQLITE_WAIT_S + sum(mlflow_tracker.RETRY_DELAYS_S))
    # the run's open of the experiment and its end each meet the lock once; a statement past the probe waits once
    assert 2 * per_call + store.BUSY_TIMEOUT_MS / 1000 < 15, per_call
    assert store.SERVER_WAIT_S <= 5


@pytest.mark.slow
def test_a_locked_or_read_only_store_costs_seconds_and_one_warning_not_the_results(tmp_path, caplog, short_waits):
    """MLflow alone waits 20 s per statement on a locked sqlite store and retries creating its engine, so
    the run used to take minutes; the store is probed first: its own waits (shortened here: BUSY_TIMEOUT_MS
    at 0.1 s, so MLflow's 20 s would show), one warning naming the store, where the results are and the
    fix, and every stage's result in the cache."""
    import sqlite3

    db = tmp_path / "mlflow.db"
    sqlite3.connect(db).close()
    cache = tmp_path / "cache"
    with _locked(db):
        start = time.monotonic()
        summary = run(compose_cfg(_tracked(tmp_path, db, ["stages=[generate]"])))
        took = time.monotonic() - start
    assert Path(summary["generate"], "index.json").is_file()
    (warning,) = _store_warnings(caplog)
    assert took < 15, took  # retried for a few seconds, not MLflow's 4 x 20 s
    assert f"MLflow store sqlite:///{db} failed while opening the experiment (OperationalError: database is locked)" \
        in warning and f"its results are in {cache}" in warning and "set tracking.uri=" in warning
    caplog.clear()
    with _read_only(db):
        summary = run(compose_cfg(_tracked(tmp_path, db, ["stages=[generate]", "generate.num_scenes=2"])))
    assert Path(summary["generate"], "index.json").is_file()
    (warning,) = _store_warnings(caplog)
    assert "readonly database" in warning and f"its results are in {cache}" in warning


@pytest.mark.slow
def test_a_store_locked_mid_run_is_given_up_in_seconds_without_mlflow_tracebacks(tmp_path, caplog, monkeypatch,
                                                                                  short_waits):
    """A lock taken after the run opened: MLflow's 20 s wait per statement is shortened (BUSY_TIMEOUT_MS)
    and its own error log with tracebacks is left out, so the run says it in one line and goes on."""
    from pairedgta.render.synthetic import SyntheticRenderer

    db = tmp_path / "mlflow.db"
    took, lock = [], contextlib.ExitStack()
    real = SyntheticRenderer.render

    def render_then_lock(self, descriptor, condition):
        if not took:
            lock.enter_context(_locked(db))
            took.append(time.monotonic())
        return real(self, descriptor, condition)

    monkeypatch.setattr(SyntheticRenderer, "render", render_then_lock)
    mlflow_log = logging.getLogger("mlflow.store.db.utils")
    mlflow_log.addHandler(caplog.handler)
    try:
        with lock:
            summary = run(compose_cfg(_tracked(tmp_path, db, ["stages=[generate]"])))
            took.append(time.monotonic())
    finally:
        mlflow_log.removeHandler(caplog.handler)
    assert Path(summary["generate"], "index.json").is_file()
    assert took[1] - took[0] < 15, took  # MLflow's own waits and retries would take 80 s or more
    (warning,) = _store_warnings(caplog)
    assert "database is locked" in warning
    assert not [r for r in caplog.records if r.name.startswith("mlflow") and r.levelno >= logging.WARNING]


@pytest.mark.slow
def test_an_unwritable_store_folder_is_one_warning_and_exit_0(tmp_path, monkeypatch):
    """Through the CLI: a store that cannot even be created still lets the stages finish, exit 0, the
    results line printed, and MLflow's failure said once."""
    from pairedgta.tracking import mlflow_tracker
    from pairedgta.testing.cli import run_cli

    monkeypatch.setattr(mlflow_tracker, "RETRY_DELAYS_S", (0.0, 0.0, 0.0))
    (tmp_path / "not_a_folder").write_text("")
    db = tmp_path / "not_a_folder" / "mlflow.db"
    proc = run_cli(_tracked(tmp_path, db, ["stages=[generate]"]), tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = [line for line in (proc.stdout + proc.stderr).splitlines() if "MLflow store" in line and "WARNING" in line]
    assert len(said) == 1 and f"sqlite:///{db}" in said[0] and "tracking.enabled=false" in said[0], said
    assert f"its results are in {tmp_path / 'cache'}" in said[0]
    assert "results: " in proc.stdout and "error:" not in proc.stderr


# --------------------------------------------------------------------------- the tracking child (pairedgta.tracking.background, .child)


@pytest.mark.slow
@pytest.mark.parametrize("store", ["sqlite", "file"])
def test_the_tracking_child_logs_what_the_run_sends_under_the_runs_pid(tmp_path, caplog, store, monkeypatch):
    """BackgroundTracker: a real child process; nested runs, a reopened run, the owner is the run's process;
    at DEBUG the run says what it waited for (the child's MLflow import and store calls). For an sqlite
    file and a `file:` folder store alike (an HTTP server: tests/test_mlflow_server.py)."""
    import mlflow

    from pairedgta.tracking import Recorder
    from pairedgta.tracking.background import BackgroundTracker
    from pairedgta.tracking.naming import RUN_COLOR_TAG, model_run_color

    uri = mlflow_store(tmp_path / "mlflow.db") if store == "sqlite" else (tmp_path / "mlruns").as_uri()
    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE", raising=False)  # the child's Tracker allows a store the user chose
    t = BackgroundTracker(uri, "bg", results=tmp_path)
    assert isinstance(t, Recorder)  # every member the app may use, data members included
    with t.run("parent"):
        t.params({"a": {"b": 1}})
        with t.run("child", nested=True):
            t.metrics({"xi_mean/Day-RAIN": 0.5})
            t.tags({"model": "demo_ddrnet"})
            child = t.run_id()
        with t.run(run_id=child, nested=True):  # reopened later, as the app does for a model's own figures
            t.config({"k": 1}, "extra.yaml")
    with caplog.at_level(logging.DEBUG, logger="pairedgta.tracking"):
        t.close()
    timings = [r.getMessage() for r in caplog.records if r.getMessage().startswith("tracking child:")]
    found = re.fullmatch(r"tracking child: MLflow import ([\d.]+) s, store calls ([\d.]+) s, waited for ([\d.]+) s "
                         r"after the run's work", timings[0]) if len(timings) == 1 else None
    assert found, timings
    assert float(found[1]) > 0.1 and float(found[2]) > 0  # MLflow was imported there; 9 calls reached the store
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # for this test's own client
    client = mlflow.tracking.MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name("bg")
    parents, nested = _runs(client, exp.experiment_id)
    assert [r.info.run_name for r in parents] == ["parent"] and [r.info.run_name for r in nested] == ["child"]
    assert {r.info.status for r in parents + nested} == {"FINISHED"}
    assert nested[0].data.tags["mlflow.parentRunId"] == parents[0].info.run_id
    assert parents[0].data.params == {"a.b": "1"} and nested[0].data.metrics == {"xi_mean/Day-RAIN": 0.5}
    assert nested[0].data.tags[RUN_COLOR_TAG] == model_run_color("demo_ddrnet")
    assert {r.data.tags["pairedgta.pid"] for r in parents + nested} == {str(os.getpid())}
    # where the run came from is the run's entry point, not the tracking child's module
    assert {r.data.tags["mlflow.source.name"] for r in parents + nested} == {sys.argv[0]}
    assert "extra.yaml" in _artifacts(client, nested[0].info.run_id)
    assert f"#/experiments/{exp.experiment_id}?workflowType=machine_learning" in t.ui_link()


@pytest.mark.slow
def test_a_failing_store_is_one_warning_in_the_runs_own_log(tmp_path, caplog):
    from pairedgta.tracking.background import BackgroundTracker

    (tmp_path / "file").write_text("a file where the store's folder should be")
    t = BackgroundTracker(f"sqlite:///{tmp_path / 'file' / 'mlflow.db'}", "bg", results=tmp_path / "cache")
    with t.run("parent"):
        t.metrics({"x": 1.0})
    t.close()
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == "pairedgta.tracking"]
    assert len(warned) == 1 and "failed while opening the experiment" in warned[0], warned
    assert f"its results are in {tmp_path / 'cache'}" in warned[0]
    assert not t.enabled and t.ui_link() is None


def test_the_child_imports_the_sql_store_only_for_a_database():
    """A second of SQLAlchemy imports per run is spent where MLflow needs it: not against a server or a folder."""
    from pairedgta.tracking.child import is_database_store

    assert is_database_store("sqlite:///outputs/mlflow.db") and is_database_store("postgresql+psycopg2://u@/mlflow?host=/s")
    assert is_database_store("mysql://u@db/mlflow")
    assert not any(is_database_store(u) for u in ("http://127.0.0.1:5000", "https://mlflow.lab.org", "file:///tmp/mlruns",
                                                  "/tmp/mlruns", "mlruns"))


@pytest.mark.slow
def test_the_child_ends_the_runs_killed_when_the_run_dies_and_the_next_run_ends_orphans(tmp_path):
    """End-of-file before `close` (kill -9 of the run): the child ends what is open KILLED. A run whose
    process and child both died stays RUNNING until the next tracker of the store ends it."""
    import io
    import pickle

    import mlflow

    from pairedgta.tracking.mlflow_tracker import Tracker
    from pairedgta.tracking.child import serve

    uri = mlflow_store(tmp_path / "mlflow.db")
    messages = [("open", (uri, "bg"), {"owner": os.getpid()}), ("begin", ("run1", "parent", False, None), {}),
                ("begin", ("run2", "model", True, None), {}), ("metrics", ({"x": 1.0},), {})]
    serve(io.BytesIO(b"".join(pickle.dumps(m) for m in messages)), io.BytesIO())
    client = mlflow.tracking.MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name("bg")
    assert sorted(r.info.status for r in client.search_runs([exp.experiment_id])) == ["KILLED", "KILLED"]

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = Tracker(uri, "bg", owner=int(gone.stdout))
    dead.begin("left running")  # its process died without unwinding: nobody ends it
    assert "RUNNING" in [r.info.status for r in client.search_runs([exp.experiment_id])]
    Tracker(uri, "bg")
    assert sorted(r.info.status for r in client.search_runs([exp.experiment_id])) == ["KILLED"] * 3


def test_the_child_is_started_before_hydra_only_where_a_run_will_log():
    from pairedgta.tracking.background import wants_prestart

    assert wants_prestart(["+experiment=paper_table"], mlflow_imported=False)
    assert not wants_prestart([], mlflow_imported=True)  # logs in-process: nothing to overlap
    for argv in (["tracking.enabled=false"], ["++tracking.background=False"], ["--help"], ["--cfg", "job"]):
        assert not wants_prestart(argv, mlflow_imported=False), argv


def test_nothing_a_library_prints_reaches_the_summary_channel(tmp_path):
    """The child's summary travels on a pipe of its own: prints from Python and from C (MLflow's "View run"
    lines against a server, a library's printf) land on stderr, never inside the pickled summary."""
    code = ("import os, pickle, sys\n"
            "from pairedgta.tracking.child import private_stdout\n"
            "channel = private_stdout()\n"
            "print('a library talks')\n"
            "sys.stdout.flush()\n"
            "os.system('echo a C library talks')\n"
            "pickle.dump({'ok': 1}, channel)\n"
            "channel.flush()\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    import pickle

    assert pickle.loads(proc.stdout) == {"ok": 1}
    assert b"a library talks" in proc.stderr and b"a C library talks" in proc.stderr


@pytest.mark.slow
def test_a_job_that_loses_the_race_to_tag_the_experiment_keeps_its_record(tmp_path, monkeypatch):
    """Jobs opening an experiment at once each see it untagged; on a server the slower one's tag write is
    a unique-key error (seen with 4 jobs on PostgreSQL), which must not switch its record off."""
    import mlflow
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    from pairedgta.tracking.mlflow_tracker import EXPERIMENT_KIND, Tracker

    uri = mlflow_store(tmp_path / "mlflow.db")
    MlflowClient(uri).create_experiment("old", artifact_location=str(tmp_path / "art"))  # an untagged experiment
    original = MlflowClient.set_experiment_tag

    def raced(self, experiment_id, key, value):
        original(self, experiment_id, key, value)  # the other job's write lands first ...
        raise MlflowException("duplicate key value violates unique constraint \"experiment_tag_pk\"")  # ... ours fails

    monkeypatch.setattr(MlflowClient, "set_experiment_tag", raced)
    # no retry: under load the first try of a job's open can spend the whole retry budget (RETRY_BUDGET_S)
    monkeypatch.setattr("pairedgta.tracking.mlflow_tracker.RETRY_DELAYS_S", ())
    tracker = Tracker(uri, "old")
    assert tracker.enabled and tracker.failed is None
    assert mlflow.MlflowClient(uri).get_experiment_by_name("old").tags[EXPERIMENT_KIND[0]] == EXPERIMENT_KIND[1]
    with tracker.run("r"):
        tracker.metrics({"m": 1.0})
    (run,) = mlflow.MlflowClient(uri).search_runs([tracker.experiment_id])
    assert run.info.status == "FINISHED" and run.data.metrics == {"m": 1.0}
