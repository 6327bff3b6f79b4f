"""The run's `tracking.*` keys, read and checked in one place, before any stage runs."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pairedgta.errors import ConfigError

DEFAULT_URI = "sqlite:///outputs/mlflow.db"


@dataclass(frozen=True)
class TrackingSettings:
    uri: str
    experiment: str  # tracking.experiment_name, else the run's `name`
    enabled: bool
    background: bool  # log from a child process (pairedgta.tracking.background)
    class_metrics: bool  # per-class xi and rho_valid as MLflow metrics too (default false: hundreds of them)

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "TrackingSettings":
        """Every flag is checked whether tracking is on or not: `maybe` or `1` is a one-line error."""
        tracking = cfg.get("tracking") or {}
        return cls(uri=tracking.get("uri", DEFAULT_URI),
                   experiment=str(tracking.get("experiment_name") or cfg.get("name", "default")),
                   enabled=_flag(tracking, "enabled"), background=_flag(tracking, "background"),
                   class_metrics=_flag(tracking, "class_metrics", default=False))


def _flag(tracking: dict[str, Any], key: str, default: bool = True) -> bool:
    value = tracking.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"tracking.{key}={value!r} must be true or false")
    return value
