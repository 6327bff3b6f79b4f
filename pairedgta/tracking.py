"""MLflow: one parent run per invocation, a nested run per evaluated model."""
from __future__ import annotations

import contextlib
import json
import logging
import math
from pathlib import Path
from typing import Any, Iterator

log = logging.getLogger("pairedgta.tracking")


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    elif isinstance(d, (list, tuple)):
        out[prefix.rstrip(".")] = json.dumps(d, default=str)
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

    @contextlib.contextmanager
    def run(self, name: str, nested: bool = False) -> Iterator[Any]:
        if not self.enabled:
            yield None
            return
        with self.mlflow.start_run(run_name=name, nested=nested) as run:
            yield run

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
