"""Content hashes of files, memoised on (path, size, mtime_ns) as DVC does: a file is read once, and
again only when its size or modification time changes. The memo is a small sqlite table under the
cache dir (safe for parallel jobs); without one, every call hashes.

Caveat shared with DVC: a file rewritten with the same size within one mtime tick keeps its old hash.
"""
from __future__ import annotations

import hashlib
import logging
import os
import sqlite3
import threading
from pathlib import Path

log = logging.getLogger(__name__)
MEMO_NAME = ".hash-memo.sqlite"
_default: "HashMemo | None" = None
_default_lock = threading.Lock()


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class HashMemo:
    def __init__(self, db: str | os.PathLike | None, verify_content: bool = False) -> None:
        self.db = Path(db) if db else None
        # cache.verify=content: every lookup re-reads the file (the memo is still written, for stat mode later)
        self.verify_content = bool(verify_content)
        self.hashed = 0  # files actually read by this object (the memo missed)
        self._conn: sqlite3.Connection | None = None

    def _connect(self) -> sqlite3.Connection | None:
        if self.db is None:
            return None
        if self._conn is None:
            try:
                self.db.parent.mkdir(parents=True, exist_ok=True)
                conn = sqlite3.connect(self.db, timeout=30, check_same_thread=False)
                conn.execute("PRAGMA journal_mode=WAL")
                conn.execute("CREATE TABLE IF NOT EXISTS memo (path TEXT PRIMARY KEY, size INTEGER, mtime_ns INTEGER, sha256 TEXT)")
                conn.commit()
                self._conn = conn
            except sqlite3.Error as exc:  # an unusable memo only costs speed
                log.warning("hash memo %s unusable (%s); hashing without it", self.db, exc)
                self.db = None
                return None
        return self._conn

    def sha256(self, path: str | os.PathLike, st: os.stat_result | None = None) -> str:
        path = os.path.abspath(path)
        st = st or os.stat(path)
        conn = self._connect()
        if conn is not None and not self.verify_content:
            row = conn.execute("SELECT size, mtime_ns, sha256 FROM memo WHERE path = ?", (path,)).fetchone()
            if row and row[0] == st.st_size and row[1] == st.st_mtime_ns:
                return str(row[2])
        digest = sha256_file(path)
        self.hashed += 1
        self.remember(path, st, digest)
        return digest

    def remember(self, path: str | os.PathLike, st: os.stat_result, digest: str) -> None:
        conn = self._connect()
        if conn is None:
            return
        try:
            conn.execute("INSERT OR REPLACE INTO memo VALUES (?, ?, ?, ?)",
                         (os.path.abspath(path), st.st_size, st.st_mtime_ns, digest))
            conn.commit()
        except sqlite3.Error as exc:  # pragma: no cover - disk full, read-only cache
            log.warning("hash memo %s: cannot record %s (%s)", self.db, path, exc)

    def remember_many(self, items: list[tuple[str, os.stat_result, str]]) -> None:
        conn = self._connect()
        if conn is None or not items:
            return
        try:
            conn.executemany("INSERT OR REPLACE INTO memo VALUES (?, ?, ?, ?)",
                             [(os.path.abspath(p), st.st_size, st.st_mtime_ns, d) for p, st, d in items])
            conn.commit()
        except sqlite3.Error as exc:  # pragma: no cover
            log.warning("hash memo %s: cannot record %d files (%s)", self.db, len(items), exc)


def set_default(cache_root: str | os.PathLike | None, verify_content: bool = False) -> HashMemo:
    """Use the memo under `cache_root` for every later `default()` caller (set by the stage cache)."""
    global _default
    with _default_lock:
        db = Path(cache_root) / MEMO_NAME if cache_root else None
        if _default is None or _default.db != db or _default.verify_content != bool(verify_content):
            _default = HashMemo(db, verify_content)
        return _default


def default() -> HashMemo:
    with _default_lock:
        return _default if _default is not None else HashMemo(None)
