"""Content-addressed stage cache: outputs/cache/<stage>/<hash>/.

The hash covers the stage's own resolved config, the hashes of its inputs and a stage version string,
nothing else. A directory only appears under its final name when complete (built under a temporary
name, then renamed), so a killed run never leaves something a later run would take as a hit, and two
jobs racing on one hash cannot corrupt each other: the first rename wins, the loser's copy is dropped.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterator

log = logging.getLogger(__name__)
MANIFEST = "manifest.json"


def canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def stage_hash(stage: str, version: str, config: Any, inputs: dict[str, str]) -> str:
    payload = canonical_json({"stage": stage, "version": version, "config": config, "inputs": inputs})
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


class StageCache:
    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def is_hit(self, stage: str, key: str) -> bool:
        return (self.path(stage, key) / MANIFEST).is_file()

    def manifest(self, stage: str, key: str) -> dict[str, Any]:
        return json.loads((self.path(stage, key) / MANIFEST).read_text())

    def partial_path(self, stage: str, key: str) -> Path:
        """A stable work directory for resumable stages (generate): never a hit, reused by a rerun."""
        return self.root / stage / f".partial-{key}"

    @contextlib.contextmanager
    def lock(self, stage: str, key: str) -> Iterator[None]:
        """Exclusive per-hash lock so parallel jobs don't compute the same stage twice; the atomic
        rename stays the guarantee where flock is unavailable (some network file systems)."""
        path = self.root / stage / f".lock-{key}"
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as handle:
            try:
                import fcntl

                fcntl.flock(handle, fcntl.LOCK_EX)
            except (ImportError, OSError):  # pragma: no cover - platform without flock
                pass
            yield

    def invalidate(self, stage: str, key: str) -> None:
        final = self.path(stage, key)
        if final.exists():
            trash = final.with_name(f".trash-{key}-{uuid.uuid4().hex[:8]}")
            os.rename(final, trash)
            shutil.rmtree(trash, ignore_errors=True)

    @contextlib.contextmanager
    def build(self, stage: str, key: str, manifest: dict[str, Any], work_dir: Path | None = None) -> Iterator[Path]:
        """Yield a temporary directory; on success write the manifest and rename it into place."""
        final = self.path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = work_dir or final.with_name(f".tmp-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        tmp.mkdir(parents=True, exist_ok=True)
        try:
            yield tmp
            (tmp / MANIFEST).write_text(json.dumps({**manifest, "stage": stage, "hash": key}, indent=2, default=str))
            try:
                os.rename(tmp, final)
            except OSError:
                if self.is_hit(stage, key):
                    log.info("%s %s was completed by another job first; keeping theirs", stage, key)
                    shutil.rmtree(tmp, ignore_errors=True)
                else:
                    raise
        except BaseException:
            if work_dir is None:
                shutil.rmtree(tmp, ignore_errors=True)
            raise
