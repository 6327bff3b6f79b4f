"""A lock on the sqlite store at any moment, its creation included, leaves the store whole and every record
FINISHED once the next run has opened it (issue 58, item 5).

The race this guards against: MLflow created a new sqlite store's schema in the file itself, ~70 alembic
migrations run statement by statement, each DDL statement committed on its own, with pysqlite's 5 s wait on a
lock. A lock taken between `CREATE TABLE _alembic_tmp_endpoints` (committed) and the `INSERT INTO` it that
follows stopped the migration half-way; every later open re-ran the migrations from the revision recorded and
failed on `table _alembic_tmp_endpoints already exists`, so no journal was ever replayed. Now the schema is
built in a private file and moved into place under the store's write lock (store.prepare_sqlite), and a store
an earlier version left half-migrated is repaired by the next run, or gets one line that says how.

The waits are shortened here (MLflow's busy timeout, pysqlite's, the probe's, the tracker's retries), so that a
lock of a fraction of a second does what a minute's lock does to a real run."""
from __future__ import annotations

import contextlib
import logging
import sqlite3
from pathlib import Path

import pytest

from pairedgta.testing.cli import locked_sqlite, mlflow_store
from pairedgta.tracking import journal as journals
from pairedgta.tracking import mlflow_tracker, store
from pairedgta.tracking.mlflow_tracker import Tracker

EXPERIMENT = "locks"
MODELS = ("m1", "m2")
BATCH_STATEMENT = "INSERT INTO _alembic_tmp_endpoints"  # where the migration stopped


@contextlib.contextmanager
def on_statement(prefix: str, action, database: Path | None = None):
    """`action()` once, just before the first SQL statement that starts with `prefix` (on `database`, or any)."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    fired: list[str] = []

    def hook(conn, cursor, statement, parameters, context, executemany):
        if not fired and statement.lstrip().startswith(prefix) and (
                database is None or Path(conn.engine.url.database or "") == database):
            fired.append(str(conn.engine.url.database))
            action()

    event.listen(Engine, "before_cursor_execute", hook)
    try:
        yield fired
    finally:
        event.remove(Engine, "before_cursor_execute", hook)


def a_run(uri: str, cache: Path, step=lambda i: None) -> Tracker:
    """One invocation's record as the app makes it: a parent run, its parameters, a nested run per model with
    tags and metrics; `step(i)` before each of its calls (0..STEPS-1), where a test takes or drops a lock."""
    tracker = Tracker(uri, EXPERIMENT, results=cache)
    i = iter(range(100))
    with tracker.run("parent"):
        step(next(i))
        tracker.params({"scenes": 3, "model": {"name": "tiny"}})
        for model in MODELS:
            step(next(i))
            with tracker.run(model, nested=True):
                step(next(i))
                tracker.tags({"model": model})
                step(next(i))
                tracker.metrics({"xi_mean": 0.5, "miou": 0.25})
        step(next(i))
        tracker.tags({"done": "yes"})
    step(next(i))
    tracker.close()
    return tracker


STEPS = 1 + 3 * len(MODELS) + 2


def records(uri: str) -> list[tuple[str, str | None, str]]:
    """(name, parent id, status) of every run in the store, and none RUNNING anywhere in it."""
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    experiments = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(experiments, max_results=1000)
    return [(r.info.run_name, r.data.tags.get("mlflow.parentRunId"), r.info.status) for r in runs]


def assert_complete(uri: str, invocations: int) -> None:
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(EXPERIMENT)
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    statuses = sorted({r.info.status for r in runs})
    assert statuses == ["FINISHED"], [(r.info.run_name, r.info.status) for r in runs]
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    nested = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == invocations and len(nested) == invocations * len(MODELS)
    assert {r.data.tags["mlflow.parentRunId"] for r in nested} == {r.info.run_id for r in parents}
    for r in parents:
        assert r.data.params["scenes"] == "3" and r.data.tags["done"] == "yes"
    for r in nested:
        assert r.data.metrics == {"xi_mean": 0.5, "miou": 0.25} and r.data.tags["model"] == r.info.run_name
        assert len(client.get_metric_history(r.info.run_id, "xi_mean")) == 1  # nothing written twice
    assert all(status != "RUNNING" for _, _, status in records(uri))


def assert_whole(db: Path) -> None:
    """The schema of this MLflow, every table, at the head revision, nothing a batch migration left."""
    from mlflow.store.db import utils

    conn = sqlite3.connect(db)
    try:
        tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        (revision,) = conn.execute("SELECT version_num FROM alembic_version").fetchone()
    finally:
        conn.close()
    assert not [t for t in tables if t.startswith("_alembic_tmp_")], tables
    assert store._expected_tables() <= set(tables)
    assert revision == utils._get_latest_schema_revision()


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == "pairedgta.tracking"]


def interrupted_creation(db: Path, hold: contextlib.ExitStack) -> None:
    """What the earlier version let happen: MLflow creating a new store in the file itself, another program
    taking the file's lock right after `CREATE TABLE _alembic_tmp_endpoints`; the migration stops there
    (`database is locked`), and MLflow alone never gets past it again."""
    from mlflow import MlflowClient

    uri = f"sqlite:///{db}"
    with on_statement(BATCH_STATEMENT, lambda: hold.enter_context(locked_sqlite(db)), db) as fired:
        with pytest.raises(Exception, match="database is locked"):
            MlflowClient(tracking_uri=uri).search_experiments()
    assert fired
    hold.close()
    with pytest.raises(Exception, match="table _alembic_tmp_endpoints already exists"):
        MlflowClient(tracking_uri=uri).search_experiments()


# -- a new store ----------------------------------------------------------------------------------------
@contextlib.contextmanager
def on_nth_statement(n: int | str, action, db: Path):
    """`action()` once, just before the `n`-th SQL statement (from 1; or the first that starts with `n`) that
    MLflow runs on the store `db` or a file beside it (the private file its schema is now built in)."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    seen: list[str] = []
    fired: list[int] = []

    def hook(conn, cursor, statement, parameters, context, executemany):
        path = Path(conn.engine.url.database or "")
        if path.parent == db.parent:
            seen.append(statement.lstrip().split("\n")[0][:80])
            if len(seen) == n or (isinstance(n, str) and seen[-1].startswith(n) and not fired):
                fired.append(len(seen))
                action()

    event.listen(Engine, "before_cursor_execute", hook)
    try:
        yield seen
    finally:
        event.remove(Engine, "before_cursor_execute", hook)


# the moments of a new store's creation the lock lands at: before it (the empty file held from the run's
# start to its end), at statements spread over MLflow's ~1700, the among them (the INSERT INTO
# _alembic_tmp_endpoints after its CREATE TABLE), and the moment the store is in place (its first experiment)
MOMENTS = ["before", 1, 21, 300, BATCH_STATEMENT, 900, 1200, 1500, 1650, "after"]


@pytest.mark.slow
def test_a_new_store_locked_during_its_creation_ten_times_has_every_record_after_the_next_run(tmp_path, short_waits,
                                                                                              caplog):
    """Ten new stores, each locked at another moment of its creation, and the next run after each: the schema
    is built in a private file while the store's own file is held by its creator, so a lock that lands
    during the migrations is refused (as by any writer) and the run's record goes in at once; a lock before
    or after costs a warning and a journal that the next run writes in. Every time: the schema whole, every
    record FINISHED after the next run, none RUNNING, no private file left."""
    cache = tmp_path / "cache"
    for n, moment in enumerate(MOMENTS):
        db = tmp_path / f"store{n}" / "mlflow.db"
        db.parent.mkdir()
        uri = f"sqlite:///{db}"
        hold = contextlib.ExitStack()
        refused: list[str] = []

        def lock_now(db=db, hold=hold, refused=refused):  # locked_sqlite, with a short wait: the migration
            holder = sqlite3.connect(db, timeout=0.2, isolation_level=None)  # waits on it in this thread
            try:
                holder.execute("BEGIN EXCLUSIVE")
            except sqlite3.OperationalError as exc:
                refused.append(str(exc))
                holder.close()
                return
            hold.callback(holder.close)  # held to the end of the run, as the 60 s lock was
            hold.callback(holder.execute, "ROLLBACK")

        caplog.clear()
        with hold:
            if moment == "before":
                hold.enter_context(locked_sqlite(db))
                a_run(uri, cache)
            elif moment == "after":
                with on_statement("INSERT INTO experiments", lock_now, db):
                    a_run(uri, cache)
            else:
                with on_nth_statement(moment, lock_now, db) as seen:
                    a_run(uri, cache)
                assert len(seen) > 1600 and refused == ["database is locked"], (moment, refused)
        said = warnings_of(caplog)
        if moment in ("before", "after"):
            assert len(said) == 1 and "database is locked" in said[0], (moment, said)
            assert journals.pending(cache, uri)
        else:
            assert not said, (moment, said)
        caplog.clear()
        a_run(uri, cache)  # the next run
        assert not warnings_of(caplog) and not journals.pending(cache, uri), moment
        assert_whole(db)
        assert_complete(uri, invocations=2)
        assert not list(db.parent.glob(".mlflow.db.*")), moment  # no private file left


# -- a store an earlier version left half-migrated ---------------------------------------------------------
@pytest.mark.slow
def test_a_store_left_half_created_is_created_anew_and_gets_every_journaled_record(tmp_path, short_waits, caplog,
                                                                                    monkeypatch):
    """The issue's store, as the earlier version left it: its creation stopped at `_alembic_tmp_endpoints`,
    two runs against it journaled their records (`database is locked`, then `table _alembic_tmp_endpoints
    already exists`, for good). The next run of this version recreates it (it held nothing), says so once,
    and writes both journals into it: every record FINISHED, none RUNNING, the schema whole."""
    db, cache = tmp_path / "mlflow.db", tmp_path / "cache"
    uri = f"sqlite:///{db}"
    hold = contextlib.ExitStack()
    monkeypatch.setattr(mlflow_tracker, "prepare_sqlite", lambda uri: None)  # the earlier version
    with hold, on_statement(BATCH_STATEMENT, lambda: hold.enter_context(locked_sqlite(db)), db):
        a_run(uri, cache)
    a_run(uri, cache)
    said = warnings_of(caplog)
    assert len(said) == 2 and "database is locked" in said[0] and "_alembic_tmp_endpoints already exists" in said[1]
    assert len(journals.pending(cache, uri)) == 2
    monkeypatch.setattr(mlflow_tracker, "prepare_sqlite", store.prepare_sqlite)  # this version
    caplog.clear()
    a_run(uri, cache)
    (said,) = warnings_of(caplog)
    assert "left half-created" in said and "_alembic_tmp_endpoints" in said and "created anew" in said
    assert not journals.pending(cache, uri)
    assert_whole(db)
    assert_complete(uri, invocations=3)


def _add_experiment(db: Path, name: str) -> None:
    conn = sqlite3.connect(db)
    with conn:
        conn.execute("INSERT INTO experiments (name, artifact_location, lifecycle_stage) VALUES (?, ?, 'active')",
                     (name, (db.parent / "mlartifacts" / name).as_uri()))
    conn.close()


@pytest.mark.slow
def test_a_half_migrated_store_that_holds_records_is_migrated_on_a_copy_and_keeps_them(tmp_path, short_waits,
                                                                                        caplog):
    """A migration of a store that holds records, stopped at the same statement: the leftover is dropped and
    the migrations run again on a copy, which takes the store's place with its records."""
    db, cache = tmp_path / "mlflow.db", tmp_path / "cache"
    uri = f"sqlite:///{db}"
    interrupted_creation(db, contextlib.ExitStack())
    _add_experiment(db, "kept")
    a_run(uri, cache)
    (said,) = warnings_of(caplog)
    assert "left half-migrated" in said and "records kept" in said
    assert_whole(db)
    assert_complete(uri, invocations=1)
    from mlflow import MlflowClient

    assert MlflowClient(tracking_uri=uri).get_experiment_by_name("kept") is not None


@pytest.mark.slow
def test_a_store_that_cannot_be_repaired_gets_one_line_that_says_how_and_then_every_record(tmp_path, short_waits,
                                                                                           caplog):
    """A leftover `_alembic_tmp_endpoints` whose table is gone (its rows may be the only copy): nothing is
    dropped; the run journals its record with one warning that says to move the store aside; done so, the
    next run creates a new store and writes the journal into it."""
    db, cache = tmp_path / "mlflow.db", tmp_path / "cache"
    uri = f"sqlite:///{db}"
    interrupted_creation(db, contextlib.ExitStack())
    _add_experiment(db, "kept")
    conn = sqlite3.connect(db)
    conn.execute("DROP TABLE endpoints")
    conn.close()
    a_run(uri, cache)
    (said,) = warnings_of(caplog)
    assert "StoreBroken" in said and f"mv {db} {db}.broken" in said and "\n" not in said
    assert journals.pending(cache, uri)
    db.rename(f"{db}.broken")  # what the line says
    caplog.clear()
    a_run(uri, cache)
    assert not warnings_of(caplog) and not journals.pending(cache, uri)
    assert_whole(db)
    assert_complete(uri, invocations=2)


# -- an existing store, locked mid-stage -----------------------------------------------------------------
@pytest.mark.slow
def test_an_existing_store_locked_mid_stage_ten_times_has_every_record_finished_after_the_next_run(
        tmp_path, short_waits, caplog):
    """Ten runs, each locked at another moment of its record (from the parent's parameters to after its end),
    the lock released inside the run or outlasting it, each followed by a plain run: after that next run,
    every record so far is FINISHED, none RUNNING, no journal left, the schema whole."""
    db, cache = tmp_path / "mlflow.db", tmp_path / "cache"
    uri = mlflow_store(db)
    for n in range(10):
        lock_at, outlasts = n % (STEPS - 1), n % 2 == 1  # a call of the run follows each of these steps
        release_at = STEPS if outlasts else min(lock_at + 2, STEPS - 1)
        hold = contextlib.ExitStack()

        def step(i, lock_at=lock_at, release_at=release_at, hold=hold):
            if i == lock_at:
                hold.enter_context(locked_sqlite(db))
            if i == release_at:
                hold.close()

        caplog.clear()
        with hold:
            a_run(uri, cache, step)
        assert len(warnings_of(caplog)) == 1, (n, warnings_of(caplog))  # the one warning of a locked store
        a_run(uri, cache)  # the next run
        assert not journals.pending(cache, uri), n
        assert_complete(uri, invocations=2 * (n + 1))
    assert_whole(db)


@pytest.mark.slow
def test_a_whole_store_is_left_as_it_is(tmp_path):
    """The common case costs one look at the table list: a whole store is neither rebuilt nor replaced."""
    db = tmp_path / "mlflow.db"
    uri = mlflow_store(db)
    inode = db.stat().st_ino
    assert store.prepare_sqlite(uri) is None and db.stat().st_ino == inode
    assert store.prepare_sqlite("http://127.0.0.1:5000") is None
