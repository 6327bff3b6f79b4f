"""The run's MLflow record, behind one interface (`Recorder`, recorder.py) that the app and the stages use:

- naming.py: run names, upload names, tags (pure functions);
- mlflow_tracker.py: `Tracker`, the Recorder that logs to MLflow in this process, with retries;
- background.py: `BackgroundTracker`, the Recorder the run holds by default, and child.py, the child
  process that replays its calls on a Tracker while the stages run (MLflow's imports off the run's path);
- store.py: the store around MLflow (URI check, sqlite probe and lock, a sqlite schema built beside the store
  and moved into place, a half-migrated store repaired, shortened waits, orphaned runs).

The `tracking.*` keys are pairedgta/schema.py's TrackingConfig. Nothing here imports mlflow until a Tracker
opens a store.
"""
from __future__ import annotations

import sys

from pairedgta.schema import RunConfig
from pairedgta.tracking import background
from pairedgta.tracking.mlflow_tracker import Tracker
from pairedgta.tracking.naming import bundle, dataset_label, run_name
from pairedgta.tracking.recorder import Recorder
from pairedgta.tracking.store import check_uri

__all__ = ["Recorder", "bundle", "dataset_label", "open_tracker", "run_name"]


def open_tracker(run: RunConfig) -> Recorder:
    """The run's Recorder: a BackgroundTracker with `tracking.background` (the default) unless this process
    has imported MLflow already (nothing to overlap), else a Tracker in this process. The experiment is
    `tracking.experiment_name`, else the run's `name`."""
    tracking = run.tracking
    experiment = str(tracking.experiment_name or run.name)
    if tracking.enabled and tracking.background and "mlflow" not in sys.modules:
        check_uri(tracking.uri)
        return background.BackgroundTracker(tracking.uri, experiment, results=run.cache_dir)
    background.discard()
    return Tracker(tracking.uri, experiment, tracking.enabled, results=run.cache_dir)
