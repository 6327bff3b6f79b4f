"""The Recorder that talks to MLflow in this process: one parent run per invocation, a nested run per
evaluated model. By default the app's calls reach it through a child process (pairedgta.tracking.child),
which imports MLflow while the run works; it is used directly where MLflow is imported already or with
`tracking.background=false`. Nothing here imports mlflow when tracking is disabled.

A stage's files are uploaded once per stage hash: a cache-hit rerun whose files an earlier run already
holds tags itself with that run (and links it in its description) instead of uploading them again. With a
sqlite store the artifacts live next to the database (store.artifact_location). Every run records the
process that owns it (store.owner_tags): a run ends FINISHED, FAILED on an error, KILLED on
Ctrl-C/SIGTERM, and a run left RUNNING by a process that died without unwinding is ended as KILLED by the
next tracker that opens the store (store.end_orphans).

MLflow is a record, not the source of truth: the stage results live in the cache. A store that fails
(locked, read-only, corrupt, full, unreachable) is retried for a few seconds (`guarded`); then the run
goes on and keeps what it could not write in a journal beside the cache (pairedgta.tracking.journal), after
one warning that names the store, the journal and the fix. The journal is written into the store at the end
of the run if the store answers again, else by the next run that opens the store, before it ends orphans.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import sys
import time
import urllib.parse
from pathlib import Path
from typing import Any, Callable, Iterator, TypeVar

from pairedgta.errors import ConfigError, Terminated
from pairedgta.tracking import journal as journals
from pairedgta.tracking.naming import RUN_COLOR_TAG, TAG, clean_metric_name, flatten, model_run_color
from pairedgta.tracking.recorder import hydra_record
from pairedgta.tracking.store import (artifact_location, check_uri, end_orphans, ensure_experiment, owner_tags,
                                      prepare_sqlite, probe_server, probe_sqlite, shorten_sqlite_waits, sqlite_path,
                                      store_lock)

log = logging.getLogger("pairedgta.tracking")


EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")

RETRY_DELAYS_S = (0.2, 0.5, 1.0)  # a locked sqlite store usually frees within a second
RETRY_BUDGET_S = 3.0  # no new try once a call has spent this long: the run does not wait on its record
T = TypeVar("T")


def guarded(what: str) -> Callable[[Callable[..., T]], Callable[..., T | None]]:
    """Run a Tracker method with retries (RETRY_DELAYS_S, within RETRY_BUDGET_S); when the store keeps
    failing, the rest of the run's record goes to a journal (this call included) with one warning; where no
    journal can be kept, MLflow is switched off for the rest of the run. The stages go on either way: their
    results are in the cache."""
    def wrap(method: Callable[..., T]) -> Callable[..., T | None]:
        @functools.wraps(method)
        def call(self: "Tracker", *args: Any, **kwargs: Any) -> T | None:
            start = time.monotonic()
            delays = iter((*RETRY_DELAYS_S, None))
            while self.enabled:
                try:
                    return method(self, *args, **kwargs)
                except (KeyboardInterrupt, Terminated, ConfigError):
                    raise
                except Exception as exc:  # sqlite, SQLAlchemy, HTTP, OSError: MLflow raises them all
                    if self.journal is not None:  # the journal itself failed (a full disk): nothing to fall back on
                        self.give_up(what, exc)
                        return None
                    delay = None if getattr(exc, "final", False) else next(delays)  # store.StoreBroken: no retry
                    if delay is None or time.monotonic() - start + delay > RETRY_BUDGET_S:
                        if not self.to_journal(what, exc):
                            self.give_up(what, exc)
                            return None
                        continue  # the same call once more, into the journal
                    time.sleep(delay)
            return None
        return call
    return wrap


def _first_line(exc: BaseException) -> str:
    """The reason in a warning; whole where it is the line that says how to repair the store (StoreBroken)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:1000 if getattr(exc, "final", False) else 200]


class Tracker:
    """The Recorder that logs to MLflow itself (the tracking child's, or the run's with
    tracking.background=false); `begin`/`finish`/`log_hydra` are the child's halves of `run`/`hydra_config`."""

    def __init__(self, uri: str, experiment: str, enabled: bool = True,
                 results: str | os.PathLike | None = None, owner: int | None = None, source: str | None = None) -> None:
        """`results`: where the run's results are whatever becomes of MLflow (the cache), for the warning;
        `owner`, `source`: the pid and entry point (its sys.argv[0]) of the run's process, when that is not
        this one (pairedgta.tracking.child): runs name the run's script and its git commit, not the child's."""
        self.owner = owner
        self.source = source
        self._context: dict[str, str] | None = None
        self._experiments: list[str] | None = None  # this store's active experiments, for cache-hit lookups
        self._ended: dict[str, str] = {}  # run id -> the status this tracker ended it with
        self._notes: dict[str, list[str]] = {}  # run id -> lines for its description, set when it ends
        self._written: dict[str, str] = {}  # run id -> its description as this tracker last set it
        # the open runs' ids, innermost last: the client API, not MLflow's fluent run stack, whose
        # start_run/end_run read the whole run back (~50 ms a call with 500 metrics)
        self._stack: list[str] = []
        self.enabled = enabled
        self.uri = uri
        self.experiment = experiment
        self.results = str(results) if results is not None else "the cache"
        self.failed: str | None = None  # why MLflow was switched off mid-run
        self.nested_tags: dict[str, str] = {}  # tags every nested run of this invocation carries (a sweep's)
        # where the record goes while the store refuses it: None until a call fails (then self.client is a
        # journal.JournalClient); kept beside the cache (`results`), never without one
        self.journal: journals.Journal | None = None
        self._root = str(results) if results is not None else None
        if enabled:
            check_uri(uri)
            self._open()

    def close(self) -> None:
        """In-process calls are done when they return (a BackgroundTracker waits here); what a failing store
        did not take is written into it now if it answers again, else left to the next run against it."""
        if self.journal is None:
            return
        journal, self.journal = self.journal, None
        try:
            if journal.entries:
                self._connect()
                applied, skipped = journals.Replay(self.client, self._experiment_of, self._log_table).run(
                    journal.path, journal._handle)
                journals.discard(journal.path)
                log.info("MLflow: the store %s answers again; the %d call(s) this run kept in %s while it failed are "
                         "in it now%s", self.uri, applied, journal.path,
                         f" ({skipped} refused by the store, see above)" if skipped else "")
                self.failed = None
            else:
                journals.discard(journal.path)
        except (KeyboardInterrupt, Terminated):
            raise
        except Exception as exc:
            self.enabled = False  # no link to a store that does not hold the run yet
            # said once as a warning when it first failed (with the journal's path): this is the outcome
            log.info("MLflow store %s still fails at the end of the run (%s: %s); this run's record stays in %s and "
                        "is written into the store when the next run opens it", self.uri, type(exc).__name__,
                        _first_line(exc), journal.path)
        finally:
            journal.close()

    def to_journal(self, what: str, exc: BaseException) -> bool:
        """The store failed for good while `what`: the rest of the run's record goes to a journal beside the
        cache. False where there is none to keep (no cache given, or it cannot be written)."""
        if self._root is None:
            return False
        try:
            self.journal = journals.Journal(self._root, self.uri, self.experiment)
        except OSError as err:
            log.debug("MLflow: no journal under %s (%s)", self._root, err)
            return False
        self.client = journals.JournalClient(self.journal)
        reason = _first_line(exc)
        self.failed = f"{what}: {type(exc).__name__}: {reason}"
        log.warning("MLflow store %s failed while %s (%s: %s); the run goes on and keeps its record in %s, written "
                    "into the store at the end of the run if it answers again, else when the next run opens it; its "
                    "results are in %s; if the store stays unusable, fix it (permissions, free space, a lock another "
                    "program holds, a corrupt database, a server that is down), or set tracking.uri= to another "
                    "store or tracking.enabled=false", self.uri, what, type(exc).__name__, reason, self.journal.path,
                    self.results)
        return True

    def give_up(self, what: str, exc: BaseException) -> None:
        reason = _first_line(exc)
        self.failed = f"{what}: {type(exc).__name__}: {reason}"
        log.warning("MLflow store %s failed while %s (%s: %s); the run goes on without it and its results are in %s; "
                    "fix the store (permissions, free space, a lock another program holds, a corrupt database), or "
                    "set tracking.uri= to another store or tracking.enabled=false", self.uri, what,
                    type(exc).__name__, reason, self.results)
        while self._stack:  # nested and parent: none is left RUNNING
            rid = self._stack.pop()
            with contextlib.suppress(Exception):
                self.client.set_terminated(rid, "FAILED")
        self.enabled = False

    def ui_link(self) -> str | None:
        """Where to look at this run's experiment: MLflow 3.17's UI opens an experiment on its GenAI
        overview unless the link asks for the runs (`workflowType=machine_learning`)."""
        eid = getattr(self, "experiment_id", None)
        if not self.enabled or eid is None:
            return None
        page = f"#/experiments/{eid}?workflowType=machine_learning"
        if self.uri.startswith(("http://", "https://")):
            return f"{self.uri.rstrip('/')}/{page}"
        return f"mlflow ui --backend-store-uri {self.uri}, then http://127.0.0.1:5000/{page}"

    @guarded("opening the experiment")
    def _open(self) -> None:
        """The store, its experiment, then what earlier runs kept in journals for this store, then the runs
        left RUNNING by processes that are gone (never one a journal still has to end)."""
        if self.journal is not None:  # the store refused: this run's record starts in the journal
            self.experiment_id = None
            return
        self._connect()
        skip: set[str] = set()
        for path in journals.pending(self._root, self.uri) if self._root is not None else []:
            if not self._replay_pending(path):
                skip |= journals.runs_of(path)
        end_orphans(self.client, skip)

    def _replay_pending(self, path: Path) -> bool:
        """True when the journal at `path` is wholly in the store now (and removed)."""
        replay = journals.Replay(self.client, self._experiment_of, self._log_table)
        result = replay.run(path)
        if result is None:
            return False  # still being written by its live run, or replayed by another run right now
        applied, skipped = result
        header, _, _ = journals.read(path)
        journals.discard(path)
        if applied:
            log.info("MLflow: %d call(s) that an earlier run (pid %s) kept in %s while the store failed are in the "
                     "store now%s", applied, header.get("pid"), path, f" ({skipped} refused)" if skipped else "")
        return True

    def _experiment_of(self, name: str) -> str:
        """The id of experiment `name` in this store, created (as `_connect` creates the run's) if missing."""
        if name == self.experiment and getattr(self, "experiment_id", None) is not None:
            return str(self.experiment_id)
        return ensure_experiment(self.client, self.uri, name, dict([EXPERIMENT_KIND]))

    def _log_table(self, frame: Any, artifact_file: str, run_id: str) -> None:
        if isinstance(self.client, journals.JournalClient):
            self.client.log_table(run_id, frame, artifact_file)
        else:
            self.mlflow.log_table(frame, artifact_file=artifact_file, run_id=run_id)

    def _connect(self) -> None:
        """Open the store and the run's experiment (raises what the store raises)."""
        # a local record: no usage telemetry sent out, and no Databricks-notebook probe (it imports
        # IPython, 0.25 s, on every run start); a user's own setting of either wins
        os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
        os.environ.setdefault("MLFLOW_ENABLE_SGC_RUN_RESUMPTION_FOR_DATABRICKS_JOBS", "false")
        # against a server MLflow prints "View run ... at: <url>" for every run it ends; the run prints one link
        os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        if urllib.parse.urlparse(self.uri).scheme in ("", "file"):  # a folder store, chosen by the user:
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow 3.17 refuses it unless told
        # a server that is down: MLflow retries each request for minutes (7 tries, backoff 2); the run's own
        # retries and its journal cover an outage, so a request gives up within seconds
        os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "2")
        os.environ.setdefault("MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR", "1")
        shorten_sqlite_waits()
        probe_server(self.uri)
        if sqlite_path(self.uri) is not None:  # its SQLAlchemy layer, imported before the lock is taken
            import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
        with store_lock(self.uri):  # parallel jobs probe in turn, never each other's locks
            probe_sqlite(self.uri)
            # a new store's schema is built beside it and moved into place, a half-migrated one repaired:
            # MLflow never migrates the file itself, where a lock could stop it half-way
            prepare_sqlite(self.uri)
        import mlflow

        mlflow.set_tracking_uri(self.uri)
        experiment, uri = self.experiment, self.uri
        with store_lock(uri):
            # parallel jobs would race on creating the sqlite schema and the experiment
            if mlflow.get_experiment_by_name(experiment) is None:
                try:
                    mlflow.create_experiment(experiment, artifact_location=artifact_location(uri, experiment),
                                             tags=dict([EXPERIMENT_KIND]))
                except mlflow.exceptions.MlflowException:  # another job (another host) created it first
                    if mlflow.get_experiment_by_name(experiment) is None:
                        raise
            found = mlflow.set_experiment(experiment)
            self.experiment_id = found.experiment_id
            self.mlflow = mlflow
            self.client = mlflow.MlflowClient()
            if EXPERIMENT_KIND[0] not in (found.tags or {}):
                # earlier MLflow 3 UIs open an experiment without this tag on the GenAI overview, not its runs;
                # 3.17 follows its sidebar switch (GenAI / Model training) instead: README says to pick the latter
                try:
                    self.client.set_experiment_tag(self.experiment_id, *EXPERIMENT_KIND)
                except mlflow.exceptions.MlflowException:  # a concurrent job set it first (a server's unique key)
                    if EXPERIMENT_KIND[0] not in (self.client.get_experiment(self.experiment_id).tags or {}):
                        raise

    def _context_tags(self) -> dict[str, str]:
        """What MLflow's start_run records about where a run comes from (user, source, git commit), read
        once: start_run asks every context provider per run, and its notebook probe imports IPython."""
        if self._context is None:
            self._context = {}
            argv = list(sys.argv)
            try:
                from mlflow.tracking.context.default_context import DefaultRunContext
                from mlflow.tracking.context.git_context import GitRunContext

                if self.source is not None:  # both read the entry point from sys.argv[0] ('' : none)
                    sys.argv[:] = [self.source] if self.source else []
                self._context = {**DefaultRunContext().tags(), **GitRunContext().tags()}
            except Exception as exc:  # pragma: no cover - private MLflow API moved: runs lose these tags only
                log.debug("MLflow context tags unavailable: %s", exc)
            finally:
                sys.argv[:] = argv
        return self._context

    @guarded("starting a run")
    def _start(self, name: str | None, nested: bool, run_id: str | None) -> Any:
        if run_id is None:  # created here, then made active: MLflow's start_run would resolve its context again
            tags = {**self._context_tags(), **owner_tags(self.owner), **(self.nested_tags if nested else {})}
            if nested and self._stack:
                tags["mlflow.parentRunId"] = self._stack[-1]
            elif self._stack:
                raise RuntimeError(f"run {self._stack[-1]} is still open; a new top-level run would hide it")
            run = self.client.create_run(self.experiment_id, run_name=name, tags=tags)
            self._stack.append(run.info.run_id)
            return run
        self._stack.append(run_id)  # reopened: it keeps its status until this ends it again
        return run_id

    @guarded("ending a run")
    def _end(self, status: str) -> None:
        rid = self._stack[-1]
        if self._ended.get(rid) != status:  # a run reopened for its figures and ended alike keeps its record
            self.client.set_terminated(rid, status)
            self._ended[rid] = status
        self._stack.pop()

    def begin(self, name: str | None = None, nested: bool = False, run_id: str | None = None) -> Any:
        """Start (or reopen) a run; None when tracking is off. `finish` ends it: `run()` pairs them."""
        return self._start(name, nested, run_id) if self.enabled else None

    def finish(self, status: str) -> None:
        self._flush_notes()
        # end this run explicitly: mlflow's own context manager would end whatever run is active
        self._end(status)

    @contextlib.contextmanager
    def run(self, name: str | None = None, nested: bool = False, run_id: str | None = None) -> Iterator[Any]:
        """A new run, or (`run_id`) one this invocation opened before, e.g. to add a model's figures."""
        run = self.begin(name, nested, run_id)
        if run is None:
            yield None
            return
        status = "FAILED"
        try:
            yield run
            status = "FINISHED"
        except (KeyboardInterrupt, Terminated):
            status = "KILLED"
            raise
        finally:
            self.finish(status)

    @guarded("naming the run")
    def rename(self, name: str) -> None:
        """The parent run is opened before generation (so a run that stops there is recorded); it gets
        its dataset's name once that is known."""
        self.client.set_tag(self._active(), "mlflow.runName", name)

    @guarded("logging parameters")
    def params(self, params: dict[str, Any]) -> None:
        if not self.enabled:
            return
        from mlflow.entities import Param

        flat = {k: str(v)[:6000] for k, v in flatten(params).items()}
        # one call: MLflow's client splits a batch into its limits (100 params, 1000 metrics a request)
        self.client.log_batch(self._active(), params=[Param(k, v) for k, v in sorted(flat.items())], synchronous=True)

    @guarded("logging metrics")
    def metrics(self, metrics: dict[str, float]) -> None:
        if not self.enabled:
            return
        clean = {clean_metric_name(k): float(v) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
        if clean:
            from mlflow.entities import Metric

            now = int(time.time() * 1000)
            self.client.log_batch(self._active(), metrics=[Metric(k, v, now, 0) for k, v in clean.items()], synchronous=True)

    @guarded("uploading artifacts")
    def artifacts(self, paths: list[Path], artifact_path: str | None = None) -> None:
        if not self.enabled:
            return
        for p in paths:
            if p.is_file():
                self.client.log_artifact(self._active(), str(p), artifact_path=artifact_path)

    @guarded("setting tags")
    def tags(self, tags: dict[str, str]) -> None:
        """Tags of the active run; a model's run (tag `model`, which only the nested runs set) also gets the
        model's figure colour (RUN_COLOR_TAG), so the UI tells the models apart as the figures do."""
        if self.enabled:
            if "model" in tags and RUN_COLOR_TAG not in tags:
                tags = {**tags, RUN_COLOR_TAG: model_run_color(str(tags["model"]))}
            self._set_tags(tags)

    # -- richer records: stage files once per hash, tables, datasets, configs ------------------------------
    def run_id(self) -> str | None:
        if not self.enabled:
            return None
        return self._stack[-1] if self._stack else None

    def _active(self) -> str:
        if not self._stack:
            raise RuntimeError("no MLflow run is open")
        return self._stack[-1]

    def _set_tags(self, tags: dict[str, Any]) -> None:
        from mlflow.entities import RunTag

        self.client.log_batch(self._active(), tags=[RunTag(k, str(v)) for k, v in tags.items()], synchronous=True)

    def _uploaded_by(self, bundle: str) -> Any:
        """The earliest run (any experiment of this store) that uploaded `bundle`, or None."""
        if self._experiments is None:  # once a run: a bundle in an experiment made since is uploaded again, no harm
            self._experiments = [e.experiment_id for e in self.client.search_experiments()]  # active: no deleted run
        runs = self.client.search_runs(self._experiments, filter_string=f"tags.`{TAG}uploaded.{bundle}` = 'true'",
                                       order_by=["attributes.start_time ASC"], max_results=1)
        return runs[0] if runs else None

    @guarded("recording stage files")
    def stage_files(self, bundle: str, hit: bool, paths: list[Path], artifact_path: str | None = None,
                    tables: dict[str, Any] | None = None) -> str | None:
        """Upload one stage result's files (`bundle` = `<stage>.<hash>[.<part>]`) and MLflow tables
        (`{artifact_file: DataFrame}`), unless this is a cache hit and an earlier run holds them: then tag
        and link that run and upload nothing. Returns the id of the run that holds the files."""
        if not self.enabled:
            return None
        earlier = self._uploaded_by(bundle) if hit else None
        if earlier is not None and earlier.info.run_id != self.run_id():
            rid, eid = earlier.info.run_id, earlier.info.experiment_id
            link = f"#/experiments/{eid}/runs/{rid}"
            if self.uri.startswith(("http://", "https://")):
                link = self.uri.rstrip("/") + "/" + link
            self._set_tags({f"{TAG}reused.{bundle}": rid, f"{TAG}reused_run": rid, f"{TAG}reused_link": link,
                            f"{TAG}cache_hit": "true"})
            self._note(f"Cache hit: `{bundle}` was uploaded by [{earlier.info.run_name or rid}]({link}).")
            log.info("tracking: %s reused from run %s (not uploaded again)", bundle, rid)
            return rid
        self.artifacts(paths, artifact_path)
        for artifact_file, frame in (tables or {}).items():
            self._log_table(frame, artifact_file, self._active())
        self._set_tags({f"{TAG}uploaded.{bundle}": "true"})
        return self.run_id()

    def _note(self, line: str) -> None:
        """A line for the active run's description (markdown, shown on the run page), written when it ends."""
        lines = self._notes.setdefault(str(self.run_id()), [])
        if line not in lines:
            lines.append(line)

    @guarded("describing the run")
    def _flush_notes(self) -> None:
        rid = self.run_id() if self.enabled else None
        lines = self._notes.pop(str(rid), None)
        if not lines:
            return
        old = self._written.get(str(rid), "")  # every run this tracker writes to, it opened
        new = [line for line in lines if line not in old]
        if new:
            self._written[str(rid)] = "\n\n".join(([old] if old else []) + new)
            self.client.set_tag(str(rid), "mlflow.note.content", self._written[str(rid)])

    @guarded("recording the dataset")
    def dataset(self, name: str, source: Path | str, digest: str, tags: dict[str, str] | None = None) -> None:
        """`log_input` of the data a run read: name, where it lies, and its hash as the digest."""
        if not self.enabled:
            return
        from mlflow.data.meta_dataset import MetaDataset
        from mlflow.data.sources import LocalArtifactDatasetSource

        data = MetaDataset(LocalArtifactDatasetSource(str(source)), name=name, digest=digest)
        from mlflow.entities import DatasetInput, InputTag
        from mlflow.utils.mlflow_tags import MLFLOW_DATASET_CONTEXT

        input_tags = [InputTag(MLFLOW_DATASET_CONTEXT, "evaluation"), *(InputTag(k, str(v)) for k, v in (tags or {}).items())]
        self.client.log_inputs(self._active(), [DatasetInput(data._to_mlflow_entity(), input_tags)])

    @guarded("uploading the config")
    def config(self, config: dict[str, Any], artifact_file: str = "config.yaml") -> None:
        """The resolved config as YAML, written by libyaml where PyYAML has it (MLflow's log_dict uses the
        pure-Python dumper: 0.1 s a config, five of them a run)."""
        if self.enabled:
            import yaml

            dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
            text = yaml.dump(config, Dumper=dumper, indent=2, default_flow_style=False)
            self.client.log_text(self._active(), text, artifact_file)

    def hydra_config(self) -> None:
        """The Hydra files of this job (`.hydra/config.yaml`, `hydra.yaml`, `overrides.yaml`) under `hydra/`,
        and the command-line overrides as a tag; nothing outside a Hydra app."""
        if self.enabled:
            self.log_hydra(hydra_record())

    @guarded("uploading the Hydra files")
    def log_hydra(self, record: tuple[list[Path], dict[str, str], dict[str, str]] | None) -> None:
        """`record`: what `hydra_record()` read in the run's process (a tracking child has no Hydra job)."""
        if not self.enabled or record is None:
            return
        files, tags, self.nested_tags = record
        self.artifacts(files, "hydra")
        self.tags(tags)
