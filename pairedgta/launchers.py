"""Sweeps on a SLURM cluster without an accounting database, which many university clusters and every
single-host test cluster run: submitit (behind Hydra's `submitit_slurm` launcher) asks `sacct` for each
job's state, and where accounting is off that fails on every poll. submitit then prints a warning per
poll and, worse, never learns that a job ended without a result (cancelled, killed, out of memory), so the
sweep waits forever. `install()` (called by the CLI for `-m` runs) gives submitit a watcher that asks
`squeue`, which knows every job until `MinJobAge` after its end, once `sacct` has said accounting is off,
and says so in one line."""
from __future__ import annotations

import functools
import logging
import os
import subprocess

log = logging.getLogger("pairedgta.launchers")
NOT_IN_QUEUE = "NOT_IN_QUEUE"  # ended longer ago than squeue remembers: done, with whatever result it left


def install() -> bool:
    """Replace submitit's SLURM state watcher (a class attribute shared by all its jobs) once per process;
    False where submitit is not installed."""
    try:
        from submitit.slurm import slurm
    except ImportError:
        return False
    if not isinstance(slurm.SlurmJob.watcher, _watcher_class()):
        slurm.SlurmJob.watcher = _watcher_class()(delay_s=600)
    return True


@functools.cache
def _watcher_class() -> type:
    """Defined on first use: submitit is optional (the launchers extra)."""
    from submitit.slurm.slurm import SlurmInfoWatcher

    class QueueWatcher(SlurmInfoWatcher):
        """sacct while it answers; squeue from the first "accounting storage is disabled" on."""

        accounting: bool | None = None  # unknown until sacct first answers

        def update(self) -> None:
            command = self._make_command()
            if command is None:
                return
            self._num_calls += 1
            if self.accounting is not False:
                proc = subprocess.run(command, capture_output=True)
                if proc.returncode == 0:
                    self.accounting = True
                    self._info_dict.update(self.read_info(proc.stdout))
                    self._mark_finished()
                    return
                reason = proc.stderr.decode(errors="replace").strip().splitlines()
                self.accounting = False
                log.info("SLURM accounting is off (sacct: %s): job states come from squeue",
                         reason[-1] if reason else f"exit code {proc.returncode}")
            self._from_squeue()

        def _from_squeue(self) -> None:
            wanted = {x.split("_")[0] for x in self._registered - self._finished}
            user = os.environ.get("USER") or _user()
            proc = subprocess.run(["squeue", "--noheader", "--states=all", f"--user={user}",
                                   "--format=%i|%T|%N"], capture_output=True)
            if proc.returncode != 0:
                log.debug("squeue failed: %s", proc.stderr.decode(errors="replace").strip())
                return
            lines = ["JobID|State|NodeList"] + [line for line in proc.stdout.decode(errors="replace").splitlines()
                                               if line.split("|")[0].strip().split("_")[0] in wanted]
            info = self.read_info("\n".join(lines))
            for job_id in self._registered - self._finished:  # not known any more: long over
                info.setdefault(job_id, {"JobID": job_id, "State": NOT_IN_QUEUE, "NodeList": ""})
            self._info_dict.update(info)
            self._mark_finished()

        def _mark_finished(self) -> None:
            import time

            self._last_status_check = time.time()
            for job_id in self._registered - self._finished:
                if self.is_done(job_id, mode="cache"):
                    self._finished.add(job_id)

    return QueueWatcher


def _user() -> str:
    import pwd

    return pwd.getpwuid(os.getuid()).pw_name


def in_submitit_job() -> bool:
    """True inside a job that submitit started (its environment names the job's folder)."""
    return any(key.startswith("SUBMITIT_") for key in os.environ)


def quiet_job_log() -> None:
    """Inside a submitit job, submitit's own lines ("Job completed successfully") stay in its
    `.submitit/<id>_log.*` files, so the job's `pairedgta.log` ends with the run's `results:` lines."""
    if in_submitit_job():
        logging.getLogger("submitit").propagate = False

