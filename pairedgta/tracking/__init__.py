"""The run's MLflow record, behind one interface (`Recorder`, recorder.py) that the app and the stages use:

- naming.py: run names, upload names, tags (pure functions);
- settings.py: the `tracking.*` keys, read and checked once (`TrackingSettings`);
- mlflow_tracker.py: `Tracker`, the Recorder that logs to MLflow in this process, with retries;
- background.py: `BackgroundTracker`, the Recorder the run holds by default, and child.py, the child
  process that replays its calls on a Tracker while the stages run (MLflow's imports off the run's path);
- store.py: the store around MLflow (URI check, sqlite probe and lock, shortened waits, orphaned runs).

Nothing here imports mlflow until a Tracker opens a store.
"""
from __future__ import annotations

import sys
from typing import Any

from pairedgta.tracking import background
from pairedgta.tracking.mlflow_tracker import Tracker
from pairedgta.tracking.naming import bundle, dataset_label, run_name, xi_table
from pairedgta.tracking.recorder import Recorder
from pairedgta.tracking.settings import TrackingSettings
from pairedgta.tracking.store import check_uri

__all__ = ["Recorder", "TrackingSettings", "bundle", "dataset_label", "open_tracker", "run_name", "xi_table"]


def open_tracker(cfg: dict[str, Any]) -> Recorder:
    """The run's Recorder: a BackgroundTracker with `tracking.background` (the default) unless this process
    has imported MLflow already (nothing to overlap), else a Tracker in this process."""
    s = TrackingSettings.from_config(cfg)  # every tracking key checked, whether tracking is on or not
    if s.enabled and s.background and "mlflow" not in sys.modules:
        check_uri(s.uri)
        return background.BackgroundTracker(s.uri, s.experiment, results=cfg.get("cache_dir"))
    background.discard()
    return Tracker(s.uri, s.experiment, s.enabled, results=cfg.get("cache_dir"))
