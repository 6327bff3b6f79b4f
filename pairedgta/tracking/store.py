"""The MLflow store before and around MLflow: which URIs the project takes, where a sqlite store keeps its
artifacts, a probe that fails in a second where MLflow would wait 20 s on a lock per statement (and retry
creating its engine for minutes), the shortening of MLflow's own waits on a sqlite store, and which runs
left RUNNING belong to a process that is gone (kill -9, power loss)."""
from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
from pathlib import Path
from typing import Any, Iterator
from urllib.parse import urlparse

from pairedgta.errors import ConfigError

log = logging.getLogger("pairedgta.tracking")
URI_SCHEMES = ("", "file", "sqlite", "http", "https", "postgresql", "mysql", "mssql", "databricks")
SQLITE_WAIT_S = 1.0  # how long the probe waits for a lock on a sqlite store
BUSY_TIMEOUT_MS = 2000  # MLflow's own wait on a locked sqlite store per statement (its default is 20000)
PID_TAG, HOST_TAG, START_TAG = "pairedgta.pid", "pairedgta.host", "pairedgta.started"


def check_uri(uri: str) -> None:
    """An MLflow store URI this project can use; anything else is one line before any stage runs."""
    scheme = urlparse(str(uri)).scheme.split("+", 1)[0].lower()
    if scheme not in URI_SCHEMES:
        raise ConfigError(f"tracking.uri={uri}: unknown scheme '{scheme}'; use sqlite:///PATH (the default "
                          "sqlite:///outputs/mlflow.db), a folder, http(s)://SERVER, or tracking.enabled=false")


def sqlite_path(uri: str) -> Path | None:
    """The database file of a `sqlite:///PATH` store, None for any other store."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri[len("sqlite:///"):].split("?", 1)[0])


def artifact_location(uri: str, experiment: str) -> str | None:
    """Where a new experiment stores artifacts: `<dir of the sqlite db>/mlartifacts/<experiment>`, not the
    working directory's ./mlruns; other stores (a tracking server, a file store) keep their own default."""
    if not uri.startswith("sqlite:///"):
        return None
    folder = re.sub(r"[^A-Za-z0-9_.\-]+", "_", experiment).strip("._") or "experiment"
    return (Path(uri[len("sqlite:///"):]).resolve().parent / "mlartifacts" / folder).as_uri()


@contextlib.contextmanager
def store_lock(uri: str) -> Iterator[None]:
    """Parallel jobs on one sqlite store take turns (a file lock beside it): they would race on creating
    its schema and experiment, and each would see the other's probe as a lock."""
    db = sqlite_path(uri)
    if db is None:
        yield
        return
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "a") as handle:
        try:
            import fcntl

            fcntl.flock(handle, fcntl.LOCK_EX)
        except (ImportError, OSError):  # pragma: no cover
            pass
        yield


def probe_sqlite(uri: str) -> None:
    """Raise what MLflow's first write to a sqlite store would (locked, read-only, a folder that cannot be
    made, not a database) within SQLITE_WAIT_S: a write in a transaction that is rolled back."""
    import sqlite3

    db = sqlite_path(uri)
    if db is None:
        return
    db.parent.mkdir(parents=True, exist_ok=True)
    conn = sqlite3.connect(db, timeout=SQLITE_WAIT_S, isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")
        conn.execute("CREATE TABLE IF NOT EXISTS pairedgta_probe (x)")
        conn.execute("ROLLBACK")
    finally:
        conn.close()


SERVER_WAIT_S = 2.0  # how long the probe waits for a tracking server to accept a connection


def probe_server(uri: str) -> None:
    """Raise ConnectionError within SERVER_WAIT_S when an http(s) tracking server does not accept a
    connection (down, wrong port): MLflow would retry its first request for minutes."""
    parsed = urlparse(str(uri))
    if parsed.scheme not in ("http", "https") or not parsed.hostname:
        return
    port = parsed.port or (443 if parsed.scheme == "https" else 80)
    try:
        socket.create_connection((parsed.hostname, port), timeout=SERVER_WAIT_S).close()
    except OSError as exc:
        raise ConnectionError(f"no tracking server answers at {parsed.hostname}:{port} ({exc})") from None


class _Reported(logging.Filter):
    """Drops MLflow's own warnings and errors (tracebacks included) about its store: the MLflow tracker
    retries those calls and, if they keep failing, says so in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


_REPORTED = _Reported()
_short_waits_installed = False


def shorten_sqlite_waits() -> None:
    """MLflow sets `PRAGMA busy_timeout = 20000` on every session of a sqlite store, and a retry would
    wait that long again; rewrite it to BUSY_TIMEOUT_MS (only that pragma, only on sqlite engines). A
    global SQLAlchemy hook, installed once per process, by the process that logs."""
    global _short_waits_installed
    if _short_waits_installed:
        return
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    def shorten(conn: Any, cursor: Any, statement: str, parameters: Any, context: Any, executemany: bool) -> Any:
        if conn.dialect.name == "sqlite" and statement.lstrip().upper().startswith("PRAGMA BUSY_TIMEOUT"):
            statement = f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_MS)};"
        return statement, parameters

    event.listen(Engine, "before_cursor_execute", shorten, retval=True)
    logging.getLogger("mlflow.store.db.utils").addFilter(_REPORTED)
    _short_waits_installed = True


def ensure_experiment(client: Any, uri: str, name: str, tags: dict[str, str]) -> str:
    """The id of experiment `name` in `client`'s store, created (artifacts beside a sqlite store) if missing;
    parallel jobs take turns (`store_lock`), and one that loses a race to create it takes the winner's."""
    with store_lock(uri):
        found = client.get_experiment_by_name(name)
        if found is not None:
            return str(found.experiment_id)
        try:
            return str(client.create_experiment(name, artifact_location=artifact_location(uri, name), tags=tags))
        except Exception:  # another job (another host) created it first
            found = client.get_experiment_by_name(name)
            if found is None:
                raise
            return str(found.experiment_id)


# -- who owns a run: a RUNNING run whose process is gone was left by a kill -9 ----------------------------
def process_start(pid: int) -> str:
    """Start time of process `pid` in clock ticks since boot (tells a reused pid apart), '' if unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def process_alive(pid: int, started: str) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        pass
    return not started or process_start(pid) in ("", started)


def owner_tags(pid: int | None = None) -> dict[str, str]:
    """The process a run belongs to: this one, or (`pid`) the run's process when a tracking child logs for it."""
    pid = os.getpid() if pid is None else pid
    return {PID_TAG: str(pid), HOST_TAG: socket.gethostname(), START_TAG: process_start(pid)}


def end_orphans(client: Any, skip: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """End as KILLED every RUNNING run of `client`'s store whose owning process on this host is gone, but
    those in `skip` (a journal not yet replayed still has to write their end)."""
    host = socket.gethostname()
    ended: list[str] = []
    try:
        experiments = [e.experiment_id for e in client.search_experiments()]
        runs = client.search_runs(experiments, filter_string="attributes.status = 'RUNNING'", max_results=5000) if experiments else []
    except Exception as exc:  # pragma: no cover - an unreadable store is reported by the run itself
        log.warning("MLflow: cannot look for orphaned runs (%s)", exc)
        return ended
    for r in runs:
        tags = r.data.tags
        if tags.get(HOST_TAG) != host or not str(tags.get(PID_TAG, "")).isdigit() or r.info.run_id in skip:
            continue
        if process_alive(int(tags[PID_TAG]), tags.get(START_TAG, "")):
            continue
        client.set_terminated(r.info.run_id, status="KILLED")
        ended.append(r.info.run_id)
    if ended:
        log.warning("MLflow: %d run(s) of a process that died were still RUNNING; marked KILLED", len(ended))
    return ended
