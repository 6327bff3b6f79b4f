"""The tracking child (`python -m pairedgta.tracking.child`, started by pairedgta.tracking.background):
imports MLflow at once, then replays the run's calls on a real `Tracker`.

Messages are `(method, args, kwargs)`; the only reply is the child's summary on `close`, on the child's
original stdout, which it moves off file descriptor 1 first (`private_stdout`): whatever a library in the
child prints goes to stderr, never into the summary. The pipes are private to the two processes (the
child is this package's own module, started with the run's interpreter), so pickle carries DataFrames
and paths as they are.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import sys
import time
import urllib.parse
from typing import Any

from pairedgta.tracking.mlflow_tracker import Tracker

# the Recorder calls a BackgroundTracker sends as they are (run/close are begin/finish/close; hydra_config is
# log_hydra of what the run's process read)
FORWARDED = {"rename", "params", "metrics", "tags", "stage_files", "dataset", "config", "log_hydra"}


class _Collect(logging.Handler):
    """The child's log lines, for the run's process to emit through its own loggers."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((record.name, record.levelno, record.getMessage()))


def serve(inp: Any, out: Any, import_s: float = 0.0) -> None:
    """Replay the run's calls on a real Tracker until `close` (reply with the summary) or end-of-file (the
    run's process died: end its open runs KILLED). `import_s`: how long MLflow's import took, for the
    summary, which also says how long the store calls took."""
    store_s = 0.0
    collect = _Collect()
    logging.getLogger("pairedgta").addHandler(collect)
    logging.getLogger("pairedgta").setLevel(logging.INFO)
    tracker: Tracker | None = None
    ids: dict[str, str | None] = {}
    depth = 0
    while True:
        try:
            method, args, kwargs = pickle.load(inp)
            started = time.perf_counter()
        except (EOFError, pickle.UnpicklingError, OSError):
            if tracker is not None:
                for _ in range(depth):
                    tracker.finish("KILLED")
                tracker.close()  # a journal kept while the store failed: into the store, if it answers now
            return
        try:
            if method == "open":
                spent = _import_database_store(args[0])
                import_s, started = import_s + spent, started + spent  # an import, not a store call
                tracker = Tracker(*args, **kwargs)
            elif tracker is None:
                continue
            elif method == "begin":
                handle, name, nested, reopen = args
                tracker.begin(name, nested, ids.get(reopen) if reopen else None)
                depth += 1
                if reopen is None:
                    ids[handle] = tracker.run_id()
            elif method == "finish":
                depth -= 1
                tracker.finish(*args)
            elif method == "close":
                tracker.close()
                summary = {"enabled": tracker.enabled, "failed": tracker.failed, "log": collect.lines,
                           "experiment_id": getattr(tracker, "experiment_id", None), "ui_link": tracker.ui_link(),
                           "import_s": import_s, "store_s": store_s}
                pickle.dump(summary, out)
                out.flush()
                return
            elif method in FORWARDED:
                getattr(tracker, method)(*args, **kwargs)
            else:  # a Recorder method the proxy sends and this loop does not know: said, not dropped
                raise ValueError(f"the tracking child does not know the call '{method}'")
        except Exception as exc:  # a bug here must not cost the run: stop logging, say so once
            if tracker is not None and tracker.enabled:
                tracker.give_up(f"replaying {method}", exc)
        store_s += time.perf_counter() - started


def _import_database_store(uri: str) -> float:
    """A database store's SQLAlchemy layer (a second of imports), before the Tracker takes the store's lock,
    so parallel jobs do not hold the lock while importing; a tracking server or a folder never needs it.
    Returns the seconds it took."""
    started = time.perf_counter()
    with contextlib.suppress(Exception):  # the Tracker reports a store it cannot open
        if is_database_store(uri):
            import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
    return time.perf_counter() - started


def is_database_store(uri: str) -> bool:
    """sqlite:///..., postgresql+psycopg2://..., mysql://...: a store MLflow reaches through SQLAlchemy."""
    from mlflow.store.db.db_types import DATABASE_ENGINES

    return urllib.parse.urlparse(str(uri)).scheme.split("+")[0] in DATABASE_ENGINES


def private_stdout() -> Any:
    """The summary's channel: the pipe the run reads, moved off file descriptor 1, which then points at
    stderr. Whatever a library prints (MLflow's "View run ... at" lines against a server, a C extension's
    printf) lands on stderr and can never corrupt the pickled summary."""
    sys.stdout.flush()
    channel = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    return channel


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the run decides: it sends KILLED, or dies (end-of-file)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
    channel = private_stdout()
    started = time.perf_counter()
    with contextlib.suppress(Exception):  # at once, while the run composes its config; Tracker reports failures
        import mlflow  # noqa: F401
    serve(sys.stdin.buffer, channel, import_s=time.perf_counter() - started)
    channel.flush()
    sys.stdout.flush()
    os._exit(0)  # all is written and committed: skip the second it takes to tear MLflow's modules down


if __name__ == "__main__":
    main()
