"""The record a failing store could not take, kept until it can: a local journal beside the cache.

When the MLflow store refuses a write (a lock another program holds for a minute, a server that is down, a
full disk) after the tracker's retries, the Tracker swaps its MLflow client for a `JournalClient`: every
call it would have made becomes one line of `<cache_dir>/.mlflow-journal/<store>/<started>-<pid>.jsonl`
(append-only, flushed and fsynced per line; the files a call uploads are hard-linked or copied next to it,
so a cache entry removed later does not take them along). `replay` writes the journal into the store, at
the end of the run if the store is back, else when the next run opens that store.

Replay is idempotent, so a replay killed half-way (kill -9) is simply run again: each applied entry is
followed by a `done` line; a run the journal created carries the tag `pairedgta.journal_run`, so a run
created but not yet marked done is found rather than created twice; metrics keep the timestamp they were
logged with (MLflow's database store drops an identical metric), tags and parameters are set to the same
value, artifacts overwrite the same path, and a table is written only if the run does not hold it yet.
The process that writes a journal holds an exclusive lock on it for its lifetime: no one replays a record
that is still being written, and two runs never replay the same journal at once.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Iterable

log = logging.getLogger("pairedgta.tracking")
FOLDER = ".mlflow-journal"  # under the cache: a dot folder, which the cache's sweep never lists
JOURNAL_TAG = "pairedgta.journal_run"  # on each run a journal created: found, not created again, on a second replay
LOCAL_PREFIX = "journal-"  # the id of a run created while the store refused: mapped to the store's id on replay


def store_folder(root: str | os.PathLike, uri: str) -> Path:
    """The journals of one store under `root` (the cache): one folder per store URI."""
    return Path(root) / FOLDER / hashlib.sha256(uri.encode()).hexdigest()[:16]


def _lock(handle: Any, block: bool) -> bool:
    try:
        import fcntl

        fcntl.flock(handle, fcntl.LOCK_EX | (0 if block else fcntl.LOCK_NB))
        return True
    except BlockingIOError:
        return False
    except (ImportError, OSError):  # pragma: no cover - no flock: one process per journal is all we assume
        return True


class Journal:
    """One run's journal, open for appending while the run lasts (and locked: see the module's docstring)."""

    def __init__(self, root: str | os.PathLike, uri: str, experiment: str) -> None:
        self.folder = store_folder(root, uri)
        self.folder.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        self.path = self.folder / f"{stamp}-{os.getpid()}-{uuid.uuid4().hex[:6]}.jsonl"
        self.files = self.path.with_suffix(".files")
        self._handle = open(self.path, "a", encoding="utf-8")
        _lock(self._handle, block=True)
        self._seq = 0
        self.entries = 0  # calls kept (not the header)
        self._write({"journal": 1, "uri": uri, "experiment": experiment, "pid": os.getpid(), "created": time.time()})

    def _write(self, record: dict[str, Any]) -> None:
        self._handle.write(json.dumps(record, sort_keys=True) + "\n")
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def append(self, op: str, **args: Any) -> None:
        self._seq += 1
        self._write({"seq": self._seq, "op": op, "args": args})
        self.entries += 1

    def keep_file(self, source: str | os.PathLike) -> str:
        """A copy of `source` that outlives the cache entry it belongs to: a hard link where it can be."""
        self.files.mkdir(exist_ok=True)
        target = self.files / f"{self._seq + 1:06d}" / Path(source).name
        target.parent.mkdir(exist_ok=True)
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)
        return str(target.relative_to(self.folder))

    def keep_text(self, text: str, name: str) -> str:
        self.files.mkdir(exist_ok=True)
        target = self.files / f"{self._seq + 1:06d}" / name
        target.parent.mkdir(exist_ok=True)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
        return str(target.relative_to(self.folder))

    def close(self) -> None:
        """Unlocks it: from now on the next run against the store may replay it."""
        with contextlib.suppress(OSError):
            self._handle.close()


class JournalClient:
    """Stands in for MlflowClient while the store refuses: each write becomes a journal entry, each search
    finds nothing (a cache hit then uploads its files again: no harm, and no guess about the store)."""

    def __init__(self, journal: Journal) -> None:
        self.journal = journal

    def create_run(self, experiment_id: Any, run_name: str | None = None, tags: dict[str, str] | None = None,
                   **_: Any) -> Any:
        rid = f"{LOCAL_PREFIX}{uuid.uuid4().hex}"
        self.journal.append("create_run", run=rid, name=run_name, tags=dict(tags or {}))
        return SimpleNamespace(info=SimpleNamespace(run_id=rid, run_name=run_name, experiment_id=None))

    def set_terminated(self, run_id: str, status: str = "FINISHED", **_: Any) -> None:
        self.journal.append("set_terminated", run=run_id, status=status, end_time=int(time.time() * 1000))

    def set_tag(self, run_id: str, key: str, value: Any, **_: Any) -> None:
        self.journal.append("log_batch", run=run_id, metrics=[], params=[], tags=[[key, str(value)]])

    def log_batch(self, run_id: str, metrics: Iterable[Any] = (), params: Iterable[Any] = (),
                  tags: Iterable[Any] = (), **_: Any) -> None:
        self.journal.append("log_batch", run=run_id,
                            metrics=[[m.key, m.value, m.timestamp, m.step] for m in metrics],
                            params=[[p.key, p.value] for p in params], tags=[[t.key, t.value] for t in tags])

    def log_artifact(self, run_id: str, local_path: str, artifact_path: str | None = None) -> None:
        self.journal.append("log_artifact", run=run_id, file=self.journal.keep_file(local_path),
                            artifact_path=artifact_path)

    def log_text(self, run_id: str, text: str, artifact_file: str) -> None:
        kept = self.journal.keep_text(text, Path(artifact_file).name)
        self.journal.append("log_artifact", run=run_id, file=kept, artifact_path=str(Path(artifact_file).parent)
                            if Path(artifact_file).parent != Path(".") else None)

    def log_table(self, run_id: str, frame: Any, artifact_file: str) -> None:
        kept = self.journal.keep_text(frame.to_json(orient="split", index=False), "table.json")
        self.journal.append("log_table", run=run_id, file=kept, artifact_file=artifact_file)

    def log_inputs(self, run_id: str, datasets: Iterable[Any], **_: Any) -> None:
        for d in datasets:
            ds = d.dataset
            self.journal.append("log_input", run=run_id, name=ds.name, digest=ds.digest, source_type=ds.source_type,
                                source=ds.source, schema=ds.schema, profile=ds.profile,
                                tags=[[t.key, t.value] for t in d.tags])

    def search_experiments(self, *_: Any, **__: Any) -> list[Any]:
        return []

    def search_runs(self, *_: Any, **__: Any) -> list[Any]:
        return []


# -- replay ----------------------------------------------------------------------------------------------
def read(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]], dict[int, dict[str, Any]]]:
    """(header, entries, done records by seq); a torn last line (the writer died mid-write) is left out."""
    header: dict[str, Any] = {}
    entries: list[dict[str, Any]] = []
    done: dict[int, dict[str, Any]] = {}
    with open(path, encoding="utf-8") as f:
        for line in f:
            try:
                record = json.loads(line)
            except ValueError:
                continue
            if "journal" in record:
                header = record
            elif "done" in record:
                done[int(record["done"])] = record
            elif "seq" in record:
                entries.append(record)
    return header, entries, done


def pending(root: str | os.PathLike, uri: str) -> list[Path]:
    folder = store_folder(root, uri)
    return sorted(folder.glob("*.jsonl")) if folder.is_dir() else []


def runs_of(path: Path) -> set[str]:
    """The store's run ids a journal writes to (those it did not create itself): the next run must not end
    them as orphans before the journal has given them their final status."""
    _, entries, done = read(path)
    created = {e["args"]["run"] for e in entries if e["op"] == "create_run"}
    ids = {str(r["run_id"]) for r in done.values() if r.get("run_id")}
    return {str(e["args"].get("run")) for e in entries if e["args"].get("run") not in created} | ids


class Replay:
    """Applies one journal's entries to a store through `client` (an MlflowClient) and `experiment_id`
    (`experiment_of(name)` gives the id of the journal's experiment, creating it where needed)."""

    def __init__(self, client: Any, experiment_of: Callable[[str], str], log_table: Callable[..., None]) -> None:
        self.client = client
        self.experiment_of = experiment_of
        self.log_table = log_table

    def run(self, path: Path, handle: Any = None) -> tuple[int, int] | None:
        """(entries applied now, entries skipped as refused by the store for good), every entry being in the
        store then; None when the journal is locked (its run is still writing it, or another run replays
        it). Raises what the store raises when it fails again (the journal stays, the rest is replayed next
        time). `handle`: the journal's own open handle where this process wrote it (and holds its lock)."""
        own = handle is None
        if own:
            try:
                handle = open(path, "a", encoding="utf-8")
            except FileNotFoundError:
                return None  # replayed and removed by another run in the meantime
            if not _lock(handle, block=False) or not path.exists():
                handle.close()
                return None
        try:
            return self._apply(path, handle)
        finally:
            if own:
                handle.close()

    def _apply(self, path: Path, handle: Any) -> tuple[int, int]:
        from mlflow.exceptions import MlflowException

        header, entries, done = read(path)
        ids = {r["local"]: r["run_id"] for r in done.values() if r.get("local")}
        applied = skipped = 0
        experiment_id = None
        for entry in entries:
            if entry["seq"] in done:
                continue
            if experiment_id is None:
                experiment_id = self.experiment_of(str(header.get("experiment") or "Default"))
            record: dict[str, Any] = {"done": entry["seq"]}
            try:
                record.update(self._one(entry["op"], entry["args"], ids, experiment_id, path.parent))
            except MlflowException as exc:
                if getattr(exc, "error_code", "") not in ("INVALID_PARAMETER_VALUE", "RESOURCE_ALREADY_EXISTS"):
                    raise
                # the store answers and refuses this one entry for good (a parameter another run set
                # differently): said, marked, and the rest goes in
                log.warning("MLflow: the journal's entry %d (%s) was refused by the store: %s", entry["seq"],
                            entry["op"], str(exc).splitlines()[0][:200])
                record["skipped"] = str(exc).splitlines()[0][:200]
                skipped += 1
            handle.write(json.dumps(record, sort_keys=True) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
            applied += 1
        return applied, skipped

    def _one(self, op: str, a: dict[str, Any], ids: dict[str, str], experiment_id: str, folder: Path) -> dict[str, Any]:
        from mlflow.entities import DatasetInput, InputTag, Metric, Param, RunTag
        from mlflow.entities import Dataset as DatasetEntity

        def real(rid: Any) -> str:
            rid = str(rid)
            if rid.startswith(LOCAL_PREFIX):
                if rid not in ids:
                    ids[rid] = self._find_or_create(rid, None, {}, experiment_id, ids)
                return ids[rid]
            return rid

        client = self.client
        if op == "create_run":
            rid = self._find_or_create(a["run"], a.get("name"), a.get("tags") or {}, experiment_id, ids)
            ids[a["run"]] = rid
            return {"local": a["run"], "run_id": rid}
        rid = real(a["run"])
        if op == "set_terminated":
            client.set_terminated(rid, a["status"], end_time=a.get("end_time"))
        elif op == "log_batch":
            tags = [RunTag(k, real(v) if k == "mlflow.parentRunId" else v) for k, v in a.get("tags") or []]
            client.log_batch(rid, metrics=[Metric(k, v, ts, step) for k, v, ts, step in a.get("metrics") or []],
                             params=[Param(k, v) for k, v in a.get("params") or []], tags=tags, synchronous=True)
        elif op == "log_artifact":
            client.log_artifact(rid, str(folder / a["file"]), artifact_path=a.get("artifact_path"))
        elif op == "log_table":
            parent = str(Path(a["artifact_file"]).parent)
            names = {f.path for f in client.list_artifacts(rid, None if parent == "." else parent)}
            if a["artifact_file"] not in names:  # MLflow's log_table appends to a table the run holds
                import pandas as pd

                frame = pd.read_json(folder / a["file"], orient="split")
                self.log_table(frame, artifact_file=a["artifact_file"], run_id=rid)
        elif op == "log_input":
            ds = DatasetEntity(a["name"], a["digest"], a["source_type"], a["source"], a.get("schema"), a.get("profile"))
            client.log_inputs(rid, [DatasetInput(ds, [InputTag(k, v) for k, v in a.get("tags") or []])])
        else:
            raise ValueError(f"unknown journal entry '{op}'")
        return {}

    def _find_or_create(self, local: str, name: str | None, tags: dict[str, str], experiment_id: str,
                        ids: dict[str, str]) -> str:
        found = self.client.search_runs([experiment_id], filter_string=f"tags.`{JOURNAL_TAG}` = '{local}'",
                                        max_results=1)
        if found:
            return found[0].info.run_id
        tags = {**tags, JOURNAL_TAG: local}
        parent = tags.get("mlflow.parentRunId")
        if parent and parent.startswith(LOCAL_PREFIX):
            tags["mlflow.parentRunId"] = ids[parent]
        return self.client.create_run(experiment_id, run_name=name, tags=tags).info.run_id


def discard(path: Path) -> None:
    """A journal wholly in the store: it and its kept files go."""
    shutil.rmtree(path.with_suffix(".files"), ignore_errors=True)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
