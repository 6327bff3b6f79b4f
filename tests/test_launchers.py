"""SLURM job states where accounting is off: sacct's refusal is said once, squeue answers instead, and a
job that ended without a result (cancelled, or long gone from the queue) counts as done, so a sweep
never waits forever. Fake `sacct`/`squeue` on PATH: runs without a cluster (tests/test_slurm.py has one)."""
from __future__ import annotations

import logging
import os
import stat

import pytest

pytest.importorskip("submitit")

from pairedgta import launchers  # noqa: E402


def _tool(folder, name, body):
    path = folder / name
    path.write_text("#!/bin/sh\n" + body)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def test_squeue_answers_once_sacct_says_accounting_is_off(tmp_path, monkeypatch, caplog):
    _tool(tmp_path, "sacct", 'echo "$*" >> "$0.calls"; echo "Slurm accounting storage is disabled" >&2; exit 1\n')
    _tool(tmp_path, "squeue", 'echo "$*" >> "$0.calls"\n'
                              'printf "7_0|CANCELLED|vm\\n7_1|RUNNING|vm\\n8_[0-1]|PENDING|\\n99|RUNNING|vm\\n"\n')
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ['PATH']}")
    watcher = launchers._watcher_class()(delay_s=600)
    for job in ("7_0", "7_1", "8_1", "5"):
        watcher.register_job(job)
    with caplog.at_level(logging.INFO, logger="pairedgta.launchers"):
        watcher.update()
        watcher.update()
    states = {job: watcher.get_state(job, mode="cache") for job in ("7_0", "7_1", "8_1", "5")}
    assert states == {"7_0": "CANCELLED", "7_1": "RUNNING", "8_1": "PENDING", "5": launchers.NOT_IN_QUEUE}
    assert watcher.is_done("7_0", mode="cache") and watcher.is_done("5", mode="cache")  # the sweep stops waiting
    assert not watcher.is_done("7_1", mode="cache")
    said = [r.getMessage() for r in caplog.records if "accounting is off" in r.getMessage()]
    assert said == ["SLURM accounting is off (sacct: Slurm accounting storage is disabled): job states come from squeue"]
    assert len((tmp_path / "sacct.calls").read_text().splitlines()) == 1  # asked once, not on every poll
    assert len((tmp_path / "squeue.calls").read_text().splitlines()) == 2


def test_install_replaces_submitits_watcher_once():
    from submitit.slurm import slurm

    saved = slurm.SlurmJob.watcher
    try:
        assert launchers.install()
        first = slurm.SlurmJob.watcher
        assert isinstance(first, launchers._watcher_class())
        launchers.install()
        assert slurm.SlurmJob.watcher is first
    finally:
        slurm.SlurmJob.watcher = saved
