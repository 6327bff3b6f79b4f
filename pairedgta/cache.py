"""Content-addressed stage cache: outputs/cache/<stage>/<hash>/.

The hash covers the stage's own resolved config, the hashes of its inputs and a stage version string,
nothing else. A directory only appears under its final name when complete (built under a temporary
name, then renamed), so a killed run never leaves something a later run would take as a hit, and two
jobs racing on one hash cannot corrupt each other: the first rename wins, the loser's copy is dropped.

Nothing is lost and nothing stale is used:
* the manifest records every file of the entry with its size and sha256; an entry is a hit only if
  every listed file is present with that size and content (content hashes memoised on path, size and
  mtime, see `pairedgta.filehash`), otherwise it is rebuilt and the log says why;
* a rebuild (``force=`` or a damaged entry) is built beside the old entry and swapped in only on
  success (an atomic exchange of the two directories where the OS has one), so a failed recompute
  leaves the previous result in place;
* a job using an entry holds a shared lock on it until it ends; a swap waits for those readers, so a
  forced recompute never pulls a dataset from under a job that is evaluating it;
* a crashed run's ``.tmp-*``/``.old-*`` folders (and, after a successful run, ``.partial-*`` ones)
  are removed once no live process holds the per-hash lock.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import logging
import os
import re
import shutil
import uuid
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Iterator

from pairedgta import filehash
from pairedgta.errors import ConfigError, write_failed
from pairedgta.jsonio import dumps, write_json

log = logging.getLogger(__name__)
MANIFEST = "manifest.json"
MANIFEST_FORMAT = 2  # 2: the manifest lists every file with size and sha256
# a resumable work directory that several jobs fill at once (generate shards): never swept as a leftover
SHARED_WORK = ".shared-by-shards"
_LEFTOVER = re.compile(r"^\.(tmp|old|trash|partial)-([0-9a-f]{16})(?:-.*)?$")


def canonical_json(obj: Any) -> str:
    return dumps(obj, sort_keys=True, separators=(",", ":"))


def stage_hash(stage: str, version: str, config: Any, inputs: dict[str, str]) -> str:
    import hashlib

    payload = canonical_json({"stage": stage, "version": version, "config": config, "inputs": inputs})
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _flock(handle: IO[Any], shared: bool = False, block: bool = True) -> bool:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - platform without flock: the atomic rename stays the guarantee
        return True
    flags = (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | (0 if block else fcntl.LOCK_NB)
    try:
        fcntl.flock(handle, flags)
        return True
    except BlockingIOError:
        return False
    except OSError:  # pragma: no cover - file system without flock (some network mounts)
        return True


_RENAME_EXCHANGE = 2
_renameat2: Any = None


def exchange(a: Path, b: Path) -> bool:
    """Atomically swap two directories (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    global _renameat2
    if _renameat2 is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            fn = libc.renameat2
            fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
            _renameat2 = fn
        except (OSError, AttributeError):
            _renameat2 = False
    if not _renameat2:
        return False
    at_fdcwd = -100
    if _renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(a))


def list_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and p.name != MANIFEST)


@dataclass(frozen=True)
class Entry:
    """A finished cache entry as `StageCache.entries` lists it."""

    key: str
    path: Path
    manifest: dict[str, Any]
    mtime: float  # the manifest's, i.e. when the entry was finished


_INSTANCES: "weakref.WeakSet[StageCache]" = weakref.WeakSet()


def release_all() -> None:
    """End every shared 'in use' lock this process holds (at the end of a run)."""
    for cache in list(_INSTANCES):
        cache.release()


VERIFY_MODES = ("stat", "content")


class StageCache:
    def __init__(self, root: str | os.PathLike, verify: str = "stat") -> None:
        """verify: `stat` trusts a file whose size and mtime match the memo (as DVC does); `content`
        re-hashes every file of an entry on every hit, and every file of an external dataset."""
        if verify not in VERIFY_MODES:
            raise ConfigError(f"cache.verify={verify!r}; use stat (trust size + mtime, the default) or content "
                              "(re-hash every file on every hit)")
        self.root = Path(root)
        self.verify = verify
        # external datasets are fingerprinted with it too
        self.memo = filehash.set_default(self.root, verify_content=verify == "content")
        self._readers: dict[tuple[str, str], IO[Any]] = {}
        self.built: set[tuple[str, str]] = set()  # entries this process built (a second force reuses them)
        self._swept = False
        _INSTANCES.add(self)

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def manifest(self, stage: str, key: str) -> dict[str, Any]:
        import json

        return json.loads((self.path(stage, key) / MANIFEST).read_text())

    def entries(self, stage: str) -> list["Entry"]:
        """The finished entries of `stage` with their manifests, by key: what a search over earlier runs
        (e.g. evaluations of other models) reads. Work and leftover folders are not entries, and one whose
        manifest cannot be read is skipped; the files are not checked here (`entry_problem` does that)."""
        import json

        found = []
        for manifest in sorted((self.root / stage).glob(f"*/{MANIFEST}")):
            d = manifest.parent
            if d.name.startswith("."):
                continue
            try:
                found.append(Entry(d.name, d, json.loads(manifest.read_text()), manifest.stat().st_mtime))
            except (OSError, json.JSONDecodeError):
                continue
        return found

    def partial_path(self, stage: str, key: str) -> Path:
        """A stable work directory for resumable stages (generate): never a hit, reused by a rerun."""
        return self.root / stage / f".partial-{key}"

    # -- validity --------------------------------------------------------------------------------
    def problem(self, stage: str, key: str) -> str | None:
        """Why the entry cannot be used (None: it can): missing, unreadable manifest, or a listed file
        missing or changed."""
        d = self.path(stage, key)
        if not (d / MANIFEST).is_file():
            return "missing" if not d.exists() else f"{d / MANIFEST} missing"
        return entry_problem(d, self.memo)

    def is_hit(self, stage: str, key: str) -> bool:
        return self.problem(stage, key) is None

    # -- locks -----------------------------------------------------------------------------------
    def _lock_file(self, stage: str, name: str) -> IO[Any]:
        path = self.root / stage / name
        path.parent.mkdir(parents=True, exist_ok=True)
        return open(path, "a")

    @contextlib.contextmanager
    def lock(self, stage: str, key: str) -> Iterator[None]:
        """Exclusive per-hash lock so parallel jobs don't compute the same stage twice; the atomic
        rename stays the guarantee where flock is unavailable (some network file systems)."""
        with self._lock_file(stage, f".lock-{key}") as handle:
            _flock(handle)
            yield

    def use(self, stage: str, key: str) -> None:
        """Mark the entry as read by this process until `release()` (or exit): a forced rebuild in
        another job waits for it before swapping."""
        if (stage, key) in self._readers:
            return
        handle = self._lock_file(stage, f".readers-{key}")
        _flock(handle, shared=True)
        self._readers[(stage, key)] = handle

    def release(self) -> None:
        for handle in self._readers.values():
            handle.close()
        self._readers.clear()

    # -- building --------------------------------------------------------------------------------
    @contextlib.contextmanager
    def build(self, stage: str, key: str, manifest: dict[str, Any], work_dir: Path | None = None,
              replace: bool = False) -> Iterator[Path]:
        """Yield a temporary directory; on success record every file in the manifest and swap it into
        place. An existing entry is replaced only now, never before: always when `replace` (force=),
        else only when it is damaged (a valid one was completed by a racing job: theirs is kept). On
        failure the temporary directory goes (a resumable `work_dir` keeps its finished parts), and a
        full disk becomes a DiskFullError naming the entry (another failed write a WriteError)."""
        final = self.path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = work_dir or final.with_name(f".tmp-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        tmp.mkdir(parents=True, exist_ok=True)
        try:
            yield tmp
            (tmp / MANIFEST).unlink(missing_ok=True)
            files, stats = {}, []
            for p in list_files(tmp):
                st = p.stat()
                digest = filehash.sha256_file(p)
                rel = p.relative_to(tmp).as_posix()
                files[rel] = {"size": st.st_size, "sha256": digest}
                stats.append((rel, st, digest))
            write_json(tmp / MANIFEST, {**manifest, "stage": stage, "hash": key, "format": MANIFEST_FORMAT,
                                        "files": files})
            self._swap_in(stage, key, tmp, final, replace)
            # renaming keeps size and mtime: the hits that follow need not read the files again
            self.memo.remember_many([(str(final / rel), st, d) for rel, st, d in stats])
            self.built.add((stage, key))
        except BaseException as exc:
            if work_dir is None:
                shutil.rmtree(tmp, ignore_errors=True)
            full = write_failed(exc, final)  # a full disk (a failed write) is one line naming the entry
            if full is not None:
                raise full from exc
            raise

    def _swap_in(self, stage: str, key: str, tmp: Path, final: Path, replace: bool) -> None:
        try:
            os.rename(tmp, final)
            return
        except OSError:
            if not final.exists():
                raise
        if not replace and self.is_hit(stage, key):
            log.info("%s %s was completed by another job first; keeping theirs", stage, key)
            shutil.rmtree(tmp, ignore_errors=True)
            return
        # replace the previous (forced or damaged) entry, but only once no other job reads it
        mine = self._readers.pop((stage, key), None)
        if mine is not None:
            mine.close()
        with self._lock_file(stage, f".readers-{key}") as readers:
            if not _flock(readers, block=False):
                log.info("%s %s: waiting for other jobs using the previous result to finish", stage, key)
                _flock(readers)
            if exchange(tmp, final):
                old = tmp
            else:  # two renames: the entry is absent for an instant, never half-written
                old = final.with_name(f".old-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
                os.rename(final, old)
                os.rename(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        log.info("%s %s: new result swapped in, previous one removed", stage, key)

    # -- leftovers -------------------------------------------------------------------------------
    def sweep(self, partials: bool = False, keep: set[tuple[str, str]] | None = None) -> list[Path]:
        """Remove what crashed runs left: .tmp-/.old-/.trash- folders (and .partial- ones when
        `partials`) whose hash no live process holds locked. Returns the removed paths."""
        removed: list[Path] = []
        if not self.root.is_dir():
            return removed
        keep = keep or set()
        for stage_dir in sorted(p for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")):
            for p in sorted(stage_dir.iterdir()):
                m = _LEFTOVER.match(p.name)
                if not m or not p.is_dir() or (m.group(1) == "partial" and not partials):
                    continue
                if m.group(1) == "partial" and (p / SHARED_WORK).exists():
                    continue  # other shard jobs may still be writing into it
                key = m.group(2)
                if (stage_dir.name, key) in keep:
                    continue
                with self._lock_file(stage_dir.name, f".lock-{key}") as handle:
                    if not _flock(handle, block=False):
                        continue  # a live job is building this hash
                    if p.exists():
                        scenes = p / "scenes"
                        detail = f" ({sum(1 for _ in scenes.iterdir())} finished scenes)" if scenes.is_dir() else ""
                        log.warning("removing %s left by a crashed run%s", p, detail)
                        shutil.rmtree(p, ignore_errors=True)
                        removed.append(p)
        return removed

    def sweep_once(self) -> None:
        """The first stage of a run clears what crashed runs left (never a resumable .partial-)."""
        if not self._swept:
            self._swept = True
            self.sweep(partials=False)


def entry_problem(d: Path, memo: filehash.HashMemo | None = None) -> str | None:
    """Why the finished entry `d` cannot be trusted (None: every file its manifest lists is there with
    the recorded size and sha256)."""
    import json

    memo = memo or filehash.default()
    try:
        manifest = json.loads((d / MANIFEST).read_text())
    except (OSError, ValueError) as exc:
        return f"{d / MANIFEST} unreadable ({type(exc).__name__})"
    files = manifest.get("files")
    if manifest.get("format") != MANIFEST_FORMAT or not isinstance(files, dict):
        return "its manifest predates file checks (no file list)"
    for rel, rec in files.items():
        p = d / rel
        try:
            st = p.stat()
        except FileNotFoundError:
            return f"{rel} is missing"
        if st.st_size != rec.get("size"):
            return f"{rel} changed size ({st.st_size} bytes, recorded {rec.get('size')})"
    for rel, rec in files.items():
        p = d / rel
        if memo.sha256(p) != rec.get("sha256"):
            return f"{rel} changed content (sha256 differs from the manifest)"
    return None


def require_intact(d: Path, stage: str) -> None:
    """One-line DataError when a finished entry another stage reads (e.g. a collected evaluation) has
    a missing or changed file: never draw from a partial result."""
    from pairedgta.errors import DataError

    problem = entry_problem(d)
    if problem is not None:
        raise DataError(f"cached {stage} output {d} is damaged ({problem}); recompute it with force=[{stage}] "
                        f"and the run's settings, or delete {d}")
