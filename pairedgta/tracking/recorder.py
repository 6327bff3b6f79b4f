"""What the app and the stages may ask of the run's record, and nothing else. Two classes implement it:
`mlflow_tracker.Tracker` logs in this process, `background.BackgroundTracker` sends each call to a child
that replays it on a Tracker (tests/test_tracking.py checks both against this list, signatures included,
so a method added to one cannot be forgotten on the other). A store that fails costs one warning, never
the run: every method returns normally whatever becomes of MLflow."""
from __future__ import annotations

from pathlib import Path
from typing import Any, ContextManager, Protocol, runtime_checkable

from pairedgta.tracking.naming import SWEEP_TAG, TAG


@runtime_checkable
class Recorder(Protocol):
    experiment: str  # the MLflow experiment the runs go to (names them: naming.run_name)

    def run(self, name: str | None = None, nested: bool = False, run_id: str | None = None) -> ContextManager[Any]:
        """A new run (nested in the open one with `nested`), or (`run_id`, from `run_id()`) one this
        invocation opened before, reopened e.g. for a model's figures. Ends FINISHED, FAILED on an error,
        KILLED on Ctrl-C/SIGTERM."""
        ...

    def run_id(self) -> str | None:
        """The open run, as `run(run_id=...)` reopens it; None when tracking is off or no run is open."""
        ...

    def rename(self, name: str) -> None:
        """The open run's name, once what it ran on is known (the parent opens before generation)."""
        ...

    def params(self, params: dict[str, Any]) -> None:
        """Parameters of the open run; nested mappings become dotted keys."""
        ...

    def metrics(self, metrics: dict[str, float]) -> None:
        """Metrics of the open run; None and NaN values are left out."""
        ...

    def tags(self, tags: dict[str, str]) -> None:
        """Tags of the open run; a `model` tag also gives the run that model's figure colour."""
        ...

    def stage_files(self, bundle: str, hit: bool, paths: list[Path], artifact_path: str | None = None,
                    tables: dict[str, Any] | None = None) -> str | None:
        """One stage result's files and tables (`bundle`: naming.bundle), uploaded once per stage hash: a
        cache hit whose files an earlier run holds links that run instead. The id of the run that holds
        them where this process knows it, else None."""
        ...

    def dataset(self, name: str, source: Path | str, digest: str, tags: dict[str, str] | None = None) -> None:
        """The data the open run read: its name, where it lies, its hash."""
        ...

    def config(self, config: dict[str, Any], artifact_file: str = "config.yaml") -> None:
        """A resolved config, as YAML, among the open run's files."""
        ...

    def hydra_config(self) -> None:
        """This Hydra job's files and command-line overrides (nothing outside a Hydra job)."""
        ...

    def ui_link(self) -> str | None:
        """Where to look at the runs (after `close`); None when nothing was recorded."""
        ...

    def close(self) -> None:
        """Returns once everything sent is recorded (or given up on)."""
        ...


def hydra_record() -> tuple[list[Path], dict[str, str], dict[str, str]] | None:
    """This Hydra job's files, its override tags, and the tags every nested run of a sweep's job carries;
    None outside a Hydra job (or under Hydra's compose API: no job, no output folder). Read in the run's
    process: a tracking child has no Hydra job."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    if OmegaConf.is_missing(hc.runtime, "output_dir"):
        return None
    files = sorted((Path(hc.runtime.output_dir) / hc.output_subdir).glob("*.yaml")) if hc.output_subdir is not None else []
    tags = {f"{TAG}overrides": " ".join(hc.overrides.task)[:5000], f"{TAG}hydra_job": str(hc.job.name)}
    nested: dict[str, str] = {}
    if str(getattr(hc, "mode", "")).endswith("MULTIRUN"):  # the jobs of one -m sweep share this tag
        # the model runs too: a search by the tag finds them, and one chart of theirs compares the models
        nested = {SWEEP_TAG: Path(str(hc.sweep.dir)).name, f"{TAG}sweep_job": str(hc.job.num)}
        tags.update(nested)
    return files, tags, nested
