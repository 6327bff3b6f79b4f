"""MLflow: one parent run per invocation, a nested run per evaluated model.

Every run records the process that owns it (tags pairedgta.pid, pairedgta.host, pairedgta.started):
a run ends FINISHED, FAILED on an error, KILLED on Ctrl-C/SIGTERM, and a run left RUNNING by a process
that died without unwinding (kill -9, power loss) is ended as KILLED by the next tracker that starts.
"""
from __future__ import annotations

import contextlib
import logging
import math
import os
import socket
from pathlib import Path
from typing import Any, Iterator

from pairedgta.errors import Terminated
from pairedgta.jsonio import dumps

log = logging.getLogger("pairedgta.tracking")
PID_TAG, HOST_TAG, START_TAG = "pairedgta.pid", "pairedgta.host", "pairedgta.started"


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


def owner_tags() -> dict[str, str]:
    pid = os.getpid()
    return {PID_TAG: str(pid), HOST_TAG: socket.gethostname(), START_TAG: process_start(pid)}


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    elif isinstance(d, (list, tuple)):
        out[prefix.rstrip(".")] = dumps(d)
    else:
        out[prefix.rstrip(".")] = d
    return out


def _clean_metric_name(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "_-./ " else "_" for ch in name)


@contextlib.contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    if not uri.startswith("sqlite:///"):
        yield
        return
    db = Path(uri[len("sqlite:///"):])
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "a") as handle:
        try:
            import fcntl

            fcntl.flock(handle, fcntl.LOCK_EX)
        except (ImportError, OSError):  # pragma: no cover
            pass
        yield


class Tracker:
    def __init__(self, uri: str, experiment: str, enabled: bool = True) -> None:
        self.enabled = enabled
        self.uri = uri
        self.experiment = experiment
        if enabled:
            import mlflow

            mlflow.set_tracking_uri(uri)
            with _store_lock(uri):
                # parallel jobs would race on creating the sqlite schema and the experiment
                mlflow.set_experiment(experiment)
                self.mlflow = mlflow
                self.end_orphans()

    @contextlib.contextmanager
    def run(self, name: str, nested: bool = False) -> Iterator[Any]:
        if not self.enabled:
            yield None
            return
        run = self.mlflow.start_run(run_name=name, nested=nested, tags=owner_tags())
        status = "FAILED"
        try:
            yield run
            status = "FINISHED"
        except (KeyboardInterrupt, Terminated):
            status = "KILLED"
            raise
        finally:
            # end this run explicitly: mlflow's own context manager would end whatever run is active
            self.mlflow.end_run(status)

    def end_orphans(self) -> list[str]:
        """End as KILLED every RUNNING run of this store whose owning process on this host is gone."""
        client = self.mlflow.tracking.MlflowClient(tracking_uri=self.uri)
        host = socket.gethostname()
        ended = []
        try:
            experiments = [e.experiment_id for e in client.search_experiments()]
            runs = client.search_runs(experiments, filter_string="attributes.status = 'RUNNING'", max_results=5000) if experiments else []
        except Exception as exc:  # pragma: no cover - an unreadable store is reported by the run itself
            log.warning("MLflow: cannot look for orphaned runs (%s)", exc)
            return ended
        for r in runs:
            tags = r.data.tags
            if tags.get(HOST_TAG) != host or not str(tags.get(PID_TAG, "")).isdigit():
                continue
            if process_alive(int(tags[PID_TAG]), tags.get(START_TAG, "")):
                continue
            client.set_terminated(r.info.run_id, status="KILLED")
            ended.append(r.info.run_id)
        if ended:
            log.warning("MLflow: %d run(s) of a process that died were still RUNNING; marked KILLED", len(ended))
        return ended

    def params(self, params: dict[str, Any]) -> None:
        if not self.enabled:
            return
        flat = {k: str(v)[:6000] for k, v in flatten(params).items()}
        items = sorted(flat.items())
        for i in range(0, len(items), 100):
            self.mlflow.log_params(dict(items[i : i + 100]))

    def metrics(self, metrics: dict[str, float]) -> None:
        if not self.enabled:
            return
        clean = {_clean_metric_name(k): float(v) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
        if clean:
            self.mlflow.log_metrics(clean)

    def artifacts(self, paths: list[Path], artifact_path: str | None = None) -> None:
        if not self.enabled:
            return
        for p in paths:
            if p.is_file():
                self.mlflow.log_artifact(str(p), artifact_path=artifact_path)

    def tags(self, tags: dict[str, str]) -> None:
        if self.enabled:
            self.mlflow.set_tags(tags)
