"""MLflow off the run's critical path: a child process imports MLflow (about 3 s of imports, more than a
cached rerun's whole work) and logs while the stages run.

The run's process holds a `BackgroundTracker`, which has the Tracker's interface: each call is pickled
onto the child's stdin in order, and the child replays it on a real `Tracker` (same retries, same one
warning, same statuses). Runs are named by handles in the run's process, mapped to MLflow run ids in
the child. `close()` waits until the child has logged everything, then relays its log lines (the
warning of a failing store, the cache-hit notes) through the run's own loggers, so they reach the
console and the job's log file. The child has its own session: Ctrl-C reaches the run, which ends its
runs KILLED through the child; if the run's process dies (kill -9), the child reads end-of-file and
ends what is still open as KILLED. Runs carry the run's pid as owner, not the child's.

Messages are `(method, args, kwargs)`; the only reply is the child's summary on `close`, on the child's
original stdout, which it moves off file descriptor 1 first (`private_stdout`): whatever a library in
the child prints goes to stderr, never into the summary. The pipes are private to the two processes (the child is this package's own module, started with this interpreter),
so pickle carries DataFrames and paths as they are.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import time
from typing import Any, Iterator

from pairedgta.errors import Terminated
from pairedgta.tracking import Tracker, check_uri, class_metrics, flag, hydra_record, settings

log = logging.getLogger("pairedgta.tracking")
CLOSE_TIMEOUT_S = 300.0  # the child's calls are each bounded (retries within RETRY_BUDGET_S); this is a backstop


class BackgroundTracker:
    def __init__(self, uri: str, experiment: str, results: Any = None) -> None:
        self.uri, self.experiment, self.enabled = uri, experiment, True
        self.experiment_id: str | None = None
        self.failed: str | None = None
        self._stack: list[str] = []
        self._handles = 0
        self._summary: dict[str, Any] | None = None
        self._proc = _take_prestarted() or _spawn()
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._write, name="pairedgta-tracking", daemon=True)
        self._writer.start()  # the run never blocks on a full pipe while the child is still importing
        self._send("open", uri, experiment, results=None if results is None else str(results), owner=os.getpid(),
                   source=sys.argv[0] if sys.argv else "")

    def _write(self) -> None:
        assert self._proc.stdin is not None
        while (data := self._queue.get()) is not None:
            try:
                self._proc.stdin.write(data)
                self._proc.stdin.flush()
            except (BrokenPipeError, OSError):
                return  # the child is gone: close() says so
        with contextlib.suppress(OSError):
            self._proc.stdin.close()

    def _send(self, method: str, *args: Any, **kwargs: Any) -> None:
        if self._summary is None:
            self._queue.put(pickle.dumps((method, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL))

    # -- the Tracker's interface ----------------------------------------------------------------------
    @contextlib.contextmanager
    def run(self, name: str | None = None, nested: bool = False, run_id: str | None = None) -> Iterator[str]:
        """`run_id`: a handle this tracker gave out before (`run_id()`), to reopen that run."""
        if run_id is None:
            self._handles += 1
            handle = f"run{self._handles}"
        else:
            handle = run_id
        self._send("begin", handle, name, nested, run_id)
        self._stack.append(handle)
        status = "FAILED"
        try:
            yield handle
            status = "FINISHED"
        except (KeyboardInterrupt, Terminated):
            status = "KILLED"
            raise
        finally:
            self._stack.pop()
            self._send("finish", status)

    def run_id(self) -> str | None:
        return self._stack[-1] if self._stack else None

    def hydra_config(self) -> None:
        self._send("log_hydra", hydra_record())  # read here: the child has no Hydra job

    def __getattr__(self, method: str) -> Any:
        if method.startswith("_") or method not in FORWARDED:
            raise AttributeError(method)
        return lambda *args, **kwargs: self._send(method, *args, **kwargs)

    def ui_link(self) -> str | None:
        return (self._summary or {}).get("ui_link")

    def close(self) -> None:
        """Wait for the child to log everything, then relay its log lines here."""
        if self._summary is not None:
            return
        self._send("close")
        self._queue.put(None)
        waited = time.perf_counter()
        summary: dict[str, Any] = {}
        try:
            assert self._proc.stdout is not None
            summary = pickle.load(self._proc.stdout)
            self._proc.wait(CLOSE_TIMEOUT_S)
        except (EOFError, pickle.UnpicklingError, OSError, subprocess.TimeoutExpired) as exc:
            code = self._proc.poll()
            if code is None:
                self._proc.kill()
            log.warning("MLflow: the tracking process stopped before it had logged this run (%s); the run's results "
                        "are in the cache; set tracking.background=false to log in this process instead",
                        f"exit code {code}" if code is not None else type(exc).__name__)
        finally:
            self._summary = summary
        for name, level, message in summary.get("log", []):
            logging.getLogger(name).log(level, "%s", message)
        if "import_s" in summary:  # what a slow rerun waited for (hydra.verbose=pairedgta.tracking shows it)
            log.debug("tracking child: MLflow import %.2f s, store calls %.2f s, waited for %.2f s after the run's "
                      "work", summary["import_s"], summary["store_s"], time.perf_counter() - waited)
        self.enabled = bool(summary.get("enabled"))
        self.failed = summary.get("failed")
        self.experiment_id = summary.get("experiment_id")


def open_tracker(cfg: dict[str, Any]) -> "BackgroundTracker | Tracker":
    """The run's tracker: a BackgroundTracker with `tracking.background` (the default) unless this process
    has imported MLflow already (nothing to overlap), else a Tracker in this process."""
    uri, experiment, enabled = settings(cfg)
    background = flag(cfg.get("tracking") or {}, "background")  # checked whether tracking is on or not
    class_metrics(cfg)  # read by the app, checked here up front
    if enabled and background and "mlflow" not in sys.modules:
        check_uri(uri)
        return BackgroundTracker(uri, experiment, results=cfg.get("cache_dir"))
    discard()
    return Tracker.from_config(cfg)


def _spawn() -> subprocess.Popen:
    env = {**os.environ, "PYTHONWARNINGS": os.environ.get("PYTHONWARNINGS", "ignore")}
    return subprocess.Popen([sys.executable, "-m", "pairedgta.tracking_worker"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=env, start_new_session=True)


_prestarted: list[subprocess.Popen] = []
_OFF = ("tracking.enabled=false", "tracking.background=false")
_NO_RUN = ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "--resolve", "--shell-completion", "-sc")


def prestart(argv: list[str]) -> None:
    """Start the tracking child before Hydra composes the config, so that MLflow's imports overlap the
    composition and the config checks too (about 2.5 s of a cached rerun). Skipped where the command
    line turns tracking off, does not run the app, or where MLflow is imported already; a config that
    turns tracking off some other way (an experiment's file) lets the child go with `discard()`."""
    if not _prestarted and wants_prestart(argv, "mlflow" in sys.modules):
        _prestarted.append(_spawn())


def wants_prestart(argv: list[str], mlflow_imported: bool) -> bool:
    args = [a.lstrip("+").lower() for a in argv]
    return not (mlflow_imported or any(a in _NO_RUN for a in args) or any(a in _OFF for a in args))


def _take_prestarted() -> subprocess.Popen | None:
    proc = _prestarted.pop() if _prestarted else None
    return proc if proc is not None and proc.poll() is None else None


def discard() -> None:
    """The prestarted child is not needed (tracking off, or the run stopped before it began): end-of-file
    on its stdin ends it."""
    while _prestarted:
        proc = _prestarted.pop()
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()


FORWARDED = {"rename", "params", "metrics", "artifacts", "tags", "stage_files", "dataset", "config", "log_hydra"}


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
            for _ in range(depth):
                if tracker is not None:
                    tracker.finish("KILLED")
            return
        try:
            if method == "open":
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
                summary = {"enabled": tracker.enabled, "failed": tracker.failed, "log": collect.lines,
                           "experiment_id": getattr(tracker, "experiment_id", None), "ui_link": tracker.ui_link(),
                           "import_s": import_s, "store_s": store_s}
                pickle.dump(summary, out)
                out.flush()
                return
            elif method in FORWARDED:
                getattr(tracker, method)(*args, **kwargs)
        except Exception as exc:  # a bug here must not cost the run: stop logging, say so once
            if tracker is not None and tracker.enabled:
                tracker.give_up(f"replaying {method}", exc)
        store_s += time.perf_counter() - started


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
        import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
    serve(sys.stdin.buffer, channel, import_s=time.perf_counter() - started)
    channel.flush()
    sys.stdout.flush()
    os._exit(0)  # all is written and committed: skip the second it takes to tear MLflow's modules down


if __name__ == "__main__":
    main()
