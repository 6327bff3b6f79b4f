"""The MLflow store before and around MLflow: which URIs the project takes, where a sqlite store keeps its
artifacts, a sqlite store's schema created or migrated in one step (`prepare_sqlite`), a probe that fails in
a second where MLflow would wait 20 s on a lock per statement (and retry creating its engine for minutes),
the shortening of MLflow's own waits on a sqlite store, and which runs left RUNNING belong to a process that
is gone (kill -9, power loss)."""
from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import sqlite3
import time
import uuid
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


# -- a sqlite store's schema, created or migrated in one step -----------------------------------------------
# MLflow creates a new sqlite store's schema in the file itself, with ~70 alembic migrations that pysqlite runs
# statement by statement, each DDL statement committed on its own (SQLite's "batch" migrations: CREATE TABLE
# _alembic_tmp_<t>, copy, DROP <t>, rename) and with pysqlite's own 5 s wait on a lock (MLflow's busy_timeout
# is set on its sessions, not on the migration's connection). Another program that takes the file's lock
# between two of those statements for longer than 5 s stops the migration half-way (`database is locked`):
# the schema is left between two revisions, often with a `_alembic_tmp_<t>` table, and every later attempt
# fails on it (`table _alembic_tmp_endpoints already exists`). So no migration runs on the store's own file:
# the schema is built (or an existing store migrated) in a private file beside it, then moved into place with
# os.replace while this process holds the store's write lock (no other writer in between).
TMP_TABLE = "_alembic_tmp_"  # what an interrupted SQLite batch migration leaves behind
SEED_TABLES = ("alembic_version", "workspaces")  # rows a migration itself writes (not a user's record)
_BROKEN: dict[tuple[Any, ...], str] = {}  # (path, inode, size, mtime) of a store that could not be repaired


class StoreBroken(RuntimeError):
    """A store that cannot be used or repaired here; its message is the one line that says what to do.
    `final`: the tracker does not retry it (pairedgta.tracking.mlflow_tracker.guarded)."""

    final = True


def _tables(conn: sqlite3.Connection) -> list[str]:
    rows = conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall()
    return [str(r[0]) for r in rows if not str(r[0]).startswith("sqlite_")]  # not SQLite's own (sqlite_sequence)


def _expected_tables() -> set[str]:
    """The tables MLflow checks for before it migrates a store (mlflow.store.db.utils._all_tables_exist)."""
    import mlflow.store.tracking.sqlalchemy_store  # noqa: F401  (its models fill the metadata)
    from mlflow.store.db.base_sql_model import Base

    return set(Base.metadata.tables)


def _holds_records(conn: sqlite3.Connection, tables: list[str]) -> bool:
    """Whether a store holds anything but what its creation writes (alembic's version, the default
    workspace, the Default experiment) or any table that is not MLflow's: a store whose creation stopped
    half-way holds nothing, as MLflow never opened it."""
    def count(table: str, where: str = "") -> int:
        return int(conn.execute(f'SELECT count(*) FROM "{table}" {where}').fetchone()[0])

    known = _expected_tables() | set(SEED_TABLES)
    for table in tables:
        if table in SEED_TABLES:
            continue
        if table not in known and not table.startswith(TMP_TABLE):
            return True
        if table in ("experiments", "experiment_tags"):
            if count(table, "WHERE experiment_id != 0"):
                return True
        elif count(table):
            return True
    return False


def _revision(conn: sqlite3.Connection, tables: list[str]) -> str | None:
    if "alembic_version" not in tables:
        return None
    row = conn.execute("SELECT version_num FROM alembic_version").fetchone()
    return str(row[0]) if row else None


def _behind(revision: str | None) -> bool:
    """Whether MLflow's migrations would run from `revision` (None: none ran to the end); False for the
    head, and for a revision this MLflow does not know (a newer MLflow's store: MLflow itself reports it)."""
    if revision is None:
        return True
    from alembic.script import ScriptDirectory
    from mlflow.store.db import utils

    script = ScriptDirectory.from_config(utils._get_alembic_config(db_url=""))
    try:
        script.get_revision(revision)
    except Exception:
        return False
    return revision not in script.get_heads()


def _schema_state(conn: sqlite3.Connection) -> tuple[str, list[str]]:
    """('ok' | 'new' | 'half', the store's tables): 'new' with no table at all; 'half' where a migration
    stopped half-way (a `_alembic_tmp_*` table left by a batch migration, or tables missing below the head
    revision), which MLflow would migrate in the file itself; else 'ok' (MLflow will not migrate it)."""
    tables = _tables(conn)
    if not tables:
        return "new", tables
    if any(t.startswith(TMP_TABLE) for t in tables):
        return "half", tables
    if not _expected_tables() <= set(tables) and _behind(_revision(conn, tables)):
        return "half", tables
    return "ok", tables


def _build_schema(target: Path) -> None:
    """MLflow's own creation of a new store (every migration, then its Default experiment), in `target`."""
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    try:  # where MLflow puts the Default experiment's artifacts when it creates a store itself
        from mlflow.tracking._tracking_service.utils import DEFAULT_LOCAL_FILE_AND_ARTIFACT_PATH as root
    except ImportError:  # pragma: no cover - moved in another MLflow
        root = "./mlruns"
    uri = f"sqlite:///{target}"
    try:
        SqlAlchemyStore(uri, root)
    finally:
        _dispose(uri, forget=True)


def _migrate_copy(db: Path, tables: list[str], target: Path) -> None:
    """A copy of the store `db` in `target`, the leftovers of an interrupted batch migration dropped and the
    migrations run again from the revision it records (the caller holds `db`'s write lock)."""

    from mlflow.store.db import utils

    src, dst = sqlite3.connect(db, timeout=SQLITE_WAIT_S), sqlite3.connect(target)
    try:
        src.backup(dst)  # another connection than the locked one: SQLite refuses a backup mid-transaction
        for table in (t for t in tables if t.startswith(TMP_TABLE)):
            if table[len(TMP_TABLE):] not in tables:  # its rows may be the only copy of that table's
                raise StoreBroken(f"table {table} holds what {table[len(TMP_TABLE):]} held")
            dst.execute(f'DROP TABLE "{table}"')
        dst.commit()
    finally:
        src.close()
        dst.close()
    uri = f"sqlite:///{target}"
    engine = utils.create_sqlalchemy_engine(uri)
    try:
        utils._initialize_tables(engine)  # the initial tables where missing, then alembic upgrade heads
        utils._verify_schema(engine)
        if not utils._all_tables_exist(engine):
            raise StoreBroken("tables are still missing after the migrations")
    finally:
        engine.dispose()


def _dispose(uri: str, forget: bool = False) -> None:
    """Close the pooled connections MLflow keeps to `uri` (they would go on reading a file that was
    replaced); `forget`: drop its engine too (a private file no one opens again)."""
    with contextlib.suppress(Exception):  # MLflow's engine cache moved: nothing was pooled by this process
        from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

        engine = SqlAlchemyStore._engine_map.pop(uri, None) if forget else SqlAlchemyStore._engine_map.get(uri)
        if engine is not None:
            engine.dispose()


def _sync(path: Path, folder: bool = False) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if folder else 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove_stale(db: Path) -> None:
    """Private files that a process killed while it built a schema left beside the store."""
    for stale in db.parent.glob(f".{db.name}.*.schema*"):
        pid = stale.name[len(db.name) + 2:].split(".", 1)[0]
        if pid.isdigit() and not process_alive(int(pid), ""):
            with contextlib.suppress(OSError):
                stale.unlink()


def prepare_sqlite(uri: str) -> str | None:
    """A sqlite store MLflow can open without migrating its file: a new one (no file, an empty file) gets
    MLflow's schema built in a private file and moved into place; one a migration left half-way (an
    interrupted creation by an earlier version, a `_alembic_tmp_*` table, tables missing) is repaired the
    same way: built anew when it holds no record, else migrated on a copy. Returns what was done (None:
    nothing, the common case, one read of its table list). Raises sqlite3.OperationalError while another
    program holds its lock (SQLITE_WAIT_S), StoreBroken with the one line that says how to repair it where
    it cannot be. Callers hold `store_lock(uri)`, and have probed the store (`probe_sqlite`: writable)."""

    db = sqlite_path(uri)
    if db is None:
        return None
    db.parent.mkdir(parents=True, exist_ok=True)
    if Path(f"{db}-wal").exists():  # a WAL store (not MLflow's way): its file is never replaced, MLflow has it
        return None
    if db.exists() and db.stat().st_size > 0:
        conn = sqlite3.connect(db, timeout=SQLITE_WAIT_S)
        try:
            if _schema_state(conn)[0] == "ok":
                return None
        finally:
            conn.close()
    # a write from here on: this process takes the store's write lock, so that no other program writes into
    # the file between the look at it and its replacement (the file is created empty if missing)
    conn = sqlite3.connect(db, timeout=SQLITE_WAIT_S, isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")
        state, tables = _schema_state(conn)
        if state == "ok":  # another program finished it meanwhile
            return None
        # nothing is written into this file while it is locked: a journal beside it would be taken for the
        # new file's once it is replaced (and the caller's probe_sqlite has found the file writable)
        fresh = state == "new" or not _holds_records(conn, tables)
        stamp = (str(db), *(lambda st: (st.st_ino, st.st_size, st.st_mtime_ns))(db.stat()))
        if stamp in _BROKEN:  # found so by this process already (the run's start): not copied again at its end
            raise StoreBroken(_BROKEN[stamp])
        _remove_stale(db)
        private = db.with_name(f".{db.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.schema")
        started = time.perf_counter()
        try:
            if fresh:
                _build_schema(private)
            else:
                try:
                    _migrate_copy(db, tables, private)
                except (KeyboardInterrupt, SystemExit):
                    raise
                except Exception as exc:
                    reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
                    _BROKEN[stamp] = (
                        f"the MLflow store {db} was left half-migrated by an interrupted migration and cannot be "
                        f"repaired here ({reason}): move it aside (mv {db} {db}.broken; its runs stay there); the "
                        f"next run creates a new store and writes into it every record its journal keeps")
                    raise StoreBroken(_BROKEN[stamp]) from None
            _sync(private)
            os.replace(private, db)
            _sync(db.parent, folder=True)
        finally:
            for leftover in (private, private.with_name(private.name + "-journal")):
                with contextlib.suppress(OSError):
                    leftover.unlink()
        with contextlib.suppress(sqlite3.Error):
            conn.execute("ROLLBACK")
    finally:
        conn.close()
    _dispose(uri)
    what = "created" if state == "new" else ("created anew" if fresh else "migrated")
    if state != "new":  # said once, by the run that repairs it
        leftovers = [t for t in tables if t.startswith(TMP_TABLE)]
        log.warning("MLflow: the store %s was left half-%s by an interrupted migration%s; %s", db,
                    "created" if fresh else "migrated", f" ({', '.join(leftovers)})" if leftovers else "",
                    "it held no record and was created anew" if fresh else
                    "a copy of it was migrated and took its place, its records kept")
    log.debug("MLflow: store %s %s in %.1f s", db, what, time.perf_counter() - started)
    return what


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
