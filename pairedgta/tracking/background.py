"""The run's side of the background record: a child process imports MLflow (about 3 s of imports, more
than a cached rerun's whole work) and logs while the stages run (the child: pairedgta.tracking.child).

A `BackgroundTracker` is a Recorder: each call is pickled onto the child's stdin in order, and the child
replays it on a real `Tracker` (same retries, same one warning, same statuses). Runs are named by handles
in the run's process, mapped to MLflow run ids in the child. `close()` waits until the child has logged
everything, then relays its log lines (the warning of a failing store, the cache-hit notes) through the
run's own loggers, so they reach the console and the job's log file. The child has its own session:
Ctrl-C reaches the run, which ends its runs KILLED through the child; if the run's process dies (kill -9),
the child reads end-of-file and ends what is still open as KILLED. Runs carry the run's pid as owner.

The child is started before Hydra composes the config (`prestart`, from pairedgta/__main__.py), so that
MLflow's imports overlap the composition: this module imports neither MLflow nor Hydra.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pickle
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

from pairedgta.errors import Terminated
from pairedgta.tracking.recorder import hydra_record

log = logging.getLogger("pairedgta.tracking")
CHILD_MODULE = "pairedgta.tracking.child"
CLOSE_TIMEOUT_S = 300.0  # the child's calls are each bounded (retries within RETRY_BUDGET_S); this is a backstop


class BackgroundTracker:
    """The Recorder of the run's process by default: every method returns at once; `close` waits."""

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

    # -- the Recorder: each call is a message, replayed in order by the child -------------------------
    @contextlib.contextmanager
    def run(self, name: str | None = None, nested: bool = False, run_id: str | None = None) -> Iterator[Any]:
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

    def rename(self, name: str) -> None:
        self._send("rename", name)

    def params(self, params: dict[str, Any]) -> None:
        self._send("params", params)

    def metrics(self, metrics: dict[str, float]) -> None:
        self._send("metrics", metrics)

    def tags(self, tags: dict[str, str]) -> None:
        self._send("tags", tags)

    def stage_files(self, bundle: str, hit: bool, paths: list[Path], artifact_path: str | None = None,
                    tables: dict[str, Any] | None = None) -> str | None:
        """None: which run holds the files is known in the child only (the app does not ask)."""
        self._send("stage_files", bundle, hit, paths, artifact_path, tables)
        return None

    def dataset(self, name: str, source: Path | str, digest: str, tags: dict[str, str] | None = None) -> None:
        self._send("dataset", name, source, digest, tags)

    def config(self, config: dict[str, Any], artifact_file: str = "config.yaml") -> None:
        self._send("config", config, artifact_file)

    def hydra_config(self) -> None:
        self._send("log_hydra", hydra_record())  # read here: the child has no Hydra job

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


def _spawn() -> subprocess.Popen:
    env = {**os.environ, "PYTHONWARNINGS": os.environ.get("PYTHONWARNINGS", "ignore")}
    return subprocess.Popen([sys.executable, "-m", CHILD_MODULE], stdin=subprocess.PIPE,
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
