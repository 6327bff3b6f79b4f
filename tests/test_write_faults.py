"""A write that fails mid-file (a full disk, or another write error) in any stage ends the run with its one
line and nothing after it (issue 58, item 4): numpy 1.x's savez left its ZipFile open when a write failed,
and the garbage collector closing it on the closed file printed ``Exception ignored in: <function
ZipFile.__del__ ...> ... ValueError: seek of closed file`` after the error line (in a fresh interpreter, at
exit). Every stage's `.npz` now goes through `jsonio.write_npz` (built in memory, one atomic write)."""
from __future__ import annotations

import errno
import gc
import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pairedgta import jsonio
from pairedgta.testing.cli import OFFLINE, fast_overrides, run_cli

# Installed in the CLI's own interpreter before it starts: files opened for writing whose path matches
# FAULT_PATTERN share FAULT_AFTER bytes of disk; the write that would pass it writes what still fits and
# raises OSError(FAULT_ERRNO) without a file name, as write(2) does. Each refusal is noted in FAULT_LOG.
INJECT = r'''
import builtins, errno, fnmatch, io, os

PATTERN, LIMIT = os.environ["FAULT_PATTERN"], int(os.environ["FAULT_AFTER"])
CODE, LOG = getattr(errno, os.environ["FAULT_ERRNO"]), os.environ["FAULT_LOG"]
used = [0]
real_open = io.open


class Filling(io.FileIO):
    def write(self, b):
        data = memoryview(b).cast("B")
        if used[0] + len(data) > LIMIT:
            fits = max(LIMIT - used[0], 0)
            if fits:
                used[0] += super().write(data[:fits])
            with real_open(LOG, "a") as log:
                log.write(os.fspath(self.name) + "\n")
            raise OSError(CODE, os.strerror(CODE))
        used[0] += len(data)
        return super().write(b)


def filling_open(file, mode="r", buffering=-1, encoding=None, errors=None, newline=None, closefd=True, opener=None):
    if (isinstance(file, (str, os.PathLike)) and any(c in mode for c in "wxa+")
            and fnmatch.fnmatch(os.path.abspath(os.fspath(file)), PATTERN)):
        raw = Filling(file, mode.replace("b", "").replace("t", ""))
        buffered = io.BufferedRandom(raw) if "+" in mode else io.BufferedWriter(raw)
        return buffered if "b" in mode else io.TextIOWrapper(buffered, encoding=encoding or "utf-8", errors=errors,
                                                               newline=newline)
    return real_open(file, mode, buffering, encoding, errors, newline, closefd, opener)


io.open = builtins.open = filling_open
'''

MAIN = ("import sys\nsys.path.insert(0, sys.argv.pop(1))\nimport filling_disk\nfrom pairedgta.__main__ import cli\n"
        "sys.argv = ['pairedgta', *sys.argv[1:]]\ncli()\n")


def overrides(tmp: Path) -> list[str]:
    """fast_overrides with PNG and PDF figures, and an in-project tiny model (tiny_ddrnet) as the model and the
    reference: the forced reruns below run in fresh interpreters, and tiny_segformer's import of transformers was
    3 s of each of them; the writes under test are the stages' own, whichever model feeds them."""
    keep = [o for o in fast_overrides(tmp) if not o.startswith(("model=", "reference_model=", "plot.formats="))]
    return keep + ["model=tiny_ddrnet", "reference_model=tiny_ddrnet", "plot.formats=[png,pdf]"]


@pytest.fixture(scope="module")
def done(tmp_path_factory) -> Path:
    """A finished main job (PNG and PDF figures): the entries a failed forced rerun must leave as they are."""
    tmp = tmp_path_factory.mktemp("faults")
    proc = run_cli(overrides(tmp), tmp)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (tmp / "filling_disk.py").write_text(INJECT)
    return tmp


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
            and not p.name.startswith(".lock") and not p.name.startswith(".readers")}


def run_on_a_filling_disk(tmp: Path, stage: str, pattern: str, after: int, code: str = "ENOSPC"):
    """`python -m pairedgta ... force=[stage]` whose writes to files under the stage's cache matching `pattern`
    fail once `after` bytes are written; -> (the process, the files whose write failed)."""
    log = tmp / f"refused-{stage}-{code}.txt"
    log.unlink(missing_ok=True)
    env = {**os.environ, **OFFLINE, "PYTHONWARNINGS": "ignore", "FAULT_PATTERN": str(tmp / "cache" / stage / pattern),
           "FAULT_AFTER": str(after), "FAULT_ERRNO": code, "FAULT_LOG": str(log)}
    args = [*overrides(tmp), f"force=[{stage}]", f"hydra.run.dir={tmp / 'run'}"]
    proc = subprocess.run([sys.executable, "-c", MAIN, str(tmp), *args], cwd=tmp, env=env, capture_output=True,
                          text=True, timeout=600)
    return proc, log.read_text().split() if log.exists() else []


def assert_one_line_and_nothing_kept(proc, refused, before: dict, cache: Path, says: str) -> None:
    assert refused, "the disk never filled: the test did not test"
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1 and says in errors[0], proc.stderr[-3000:]
    assert lines[-1] == errors[0], proc.stderr[-3000:]  # nothing after the error line
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr[-3000:]
    assert snapshot(cache) == before  # the previous entry as it was, no temporary file or folder left


@pytest.mark.slow
def test_a_full_disk_while_evaluate_writes_its_npz_is_one_line_and_nothing_after_it(done):
    """ENOSPC part-way through evaluate's `.npz` (group_counts / predictions) in a forced rerun: exit 2, the
    one line, no `Exception ignored in ... ZipFile.__del__` after it (in 3 runs of 3 before the fix), and
    the previous entry intact with no temporary left."""
    cache = done / "cache" / "evaluate"
    before = snapshot(cache)
    for after in (0, 2000):  # at the archive's first byte, and part-way through it
        proc, refused = run_on_a_filling_disk(done, "evaluate", "*.npz*", after)
        assert all(".npz" in Path(p).name for p in refused), refused
        assert_one_line_and_nothing_kept(proc, refused, before, cache, f"no space left on the disk of {cache}/")


@pytest.mark.slow
def test_another_write_error_while_evaluate_writes_its_npz_is_one_line_too(done):
    """An input/output error (or a read-only file system) in the same place: its own one line, exit 2."""
    cache = done / "cache" / "evaluate"
    before = snapshot(cache)
    proc, refused = run_on_a_filling_disk(done, "evaluate", "*.npz*", 2000, code="EIO")
    assert_one_line_and_nothing_kept(proc, refused, before, cache, f"input/output error while writing {cache}/")


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["plot", "pseudolabel"])
def test_a_full_disk_in_another_stage_is_one_line_and_nothing_after_it(done, stage):
    """The figures (PNG and PDF through matplotlib, CSV through pandas) and the pseudo-labels (PNG through
    PIL) meet a full disk the same way."""
    cache = done / "cache" / stage
    before = snapshot(cache)
    proc, refused = run_on_a_filling_disk(done, stage, "*", 1000)
    assert_one_line_and_nothing_kept(proc, refused, before, cache, f"no space left on the disk of {cache}/")


class _Filling(io.FileIO):
    """A file on a disk with `room` bytes left."""
    room = 0

    def write(self, b):
        data = memoryview(b).cast("B")
        if len(data) > self.room:
            super().write(data[:self.room])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return super().write(b)


@pytest.mark.parametrize("room", [0, 100, 5000])
def test_write_npz_on_a_full_disk_leaves_nothing_to_the_garbage_collector(tmp_path, monkeypatch, room):
    """`write_npz` on a disk that fills up part-way: the ENOSPC reaches the caller, no temporary file is left,
    and collecting garbage afterwards runs no finaliser that fails (what printed `Exception ignored`)."""
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)

    def filling_open(file, mode="r", *args, **kwargs):
        assert mode == "wb"
        raw = _Filling(file, "w")
        raw.room = room
        return io.BufferedWriter(raw)

    monkeypatch.setattr(jsonio, "open", filling_open, raising=False)
    arrays = {"group_id": np.array(["a", "b"]), "counts": np.arange(20000, dtype=np.int64).reshape(2, -1)}
    with pytest.raises(OSError) as caught:
        jsonio.write_npz(tmp_path / "group_counts.npz", arrays)
    assert caught.value.errno == errno.ENOSPC
    del caught
    gc.collect()
    assert not unraisable, [u.exc_value for u in unraisable]
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    jsonio.write_npz(tmp_path / "group_counts.npz", arrays)  # the same bytes as numpy's own savez_compressed
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    assert (tmp_path / "group_counts.npz").read_bytes() == buf.getvalue()
    assert [p.name for p in tmp_path.iterdir()] == ["group_counts.npz"]
