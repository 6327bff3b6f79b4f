"""A single-node SLURM cluster on this machine, for the tests and for trying the cluster path by hand.

Everything lives under one folder: its own munge key and socket, `slurm.conf` (given to every SLURM
command through `SLURM_CONF`), state, spool, logs and pid files, on ports chosen free at start; nothing
in /etc is touched and nothing is left running after `stop()`. Debian's `slurm-wlm` and `munge` provide
the daemons (`.ci/run` installs them). The settings are the ones a single host without cgroups needs
(`ProctrackType=proctrack/linuxproc`, `TaskPlugin=task/none`, no cgroup.conf) and, like many small
clusters, no accounting database: `sacct` answers "accounting storage is disabled".

    python -m pairedgta.testing.slurm start DIR   # prints the export line for SLURM_CONF
    python -m pairedgta.testing.slurm stop DIR
"""
from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "squeue", "scancel", "sinfo")
PARTITION = "debug"


class Unavailable(RuntimeError):
    """SLURM cannot run here; the message says exactly why (for a test's skip line)."""


def _which(name: str) -> str | None:
    return shutil.which(name) or next((str(p) for p in (Path("/usr/sbin") / name, Path("/sbin") / name)
                                       if p.is_file()), None)


def missing_binaries() -> list[str]:
    return [name for name in (*DAEMONS, *CLIENTS) if _which(name) is None]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node_line() -> str:
    """This host as slurmd sees it (`slurmd -C`), with a little memory left to the system."""
    out = subprocess.run([_which("slurmd") or "slurmd", "-C"], capture_output=True, text=True, timeout=30).stdout
    fields = dict(f.split("=", 1) for f in out.split() if "=" in f)
    if "NodeName" not in fields:
        raise Unavailable(f"`slurmd -C` did not describe this host: {out.strip()[:200]!r}")
    memory = max(1024, int(fields.get("RealMemory", "2048")) - 1024)
    return f"NodeName={fields['NodeName']} NodeAddr=127.0.0.1 CPUs={fields.get('CPUs', '1')} RealMemory={memory} State=UNKNOWN"


class Cluster:
    """`start()` brings munged, slurmctld and slurmd up under `root`; `env` is what a SLURM client needs."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.conf = self.root / "slurm.conf"
        self.env = {"SLURM_CONF": str(self.conf)}

    # -- lifecycle ------------------------------------------------------------------------------------
    def start(self, timeout_s: float = 60.0) -> "Cluster":
        if missing_binaries():
            raise Unavailable(f"SLURM is not installed ({', '.join(missing_binaries())} missing); "
                              "install Debian's slurm-wlm and munge (apt-get install slurm-wlm munge)")
        if os.geteuid() != 0:
            raise Unavailable("starting slurmd needs root (it launches the jobs); run as root, as CI does")
        for sub in ("state", "spool", "log", "munge"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._start_munge()
        node = _node_line()
        self.node = node.split()[0].split("=", 1)[1]
        self.conf.write_text("\n".join([
            "ClusterName=pairedgta-test",
            f"SlurmctldHost={self.node}(127.0.0.1)",
            f"SlurmctldPort={_free_port()}",
            f"SlurmdPort={_free_port()}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.root / 'munge' / 'munge.socket'}",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "SchedulerType=sched/backfill",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core",
            "ReturnToService=2",
            "MpiDefault=none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "JobCompType=jobcomp/none",
            "MinJobAge=600",
            "SlurmdTimeout=60",
            "KillWait=5",
            f"StateSaveLocation={self.root / 'state'}",
            f"SlurmdSpoolDir={self.root / 'spool'}",
            f"SlurmctldPidFile={self.root / 'slurmctld.pid'}",
            f"SlurmdPidFile={self.root / 'slurmd.pid'}",
            f"SlurmctldLogFile={self.root / 'log' / 'slurmctld.log'}",
            f"SlurmdLogFile={self.root / 'log' / 'slurmd.log'}",
            node,
            f"PartitionName={PARTITION} Nodes=ALL Default=YES MaxTime=INFINITE State=UP OverSubscribe=FORCE:4",
            "",
        ]))
        env = {**os.environ, **self.env}
        self._daemon([_which("slurmctld"), "-i", "-f", str(self.conf)], env)
        self._daemon([_which("slurmd"), "-f", str(self.conf)], env)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out = subprocess.run([_which("sinfo"), "-h", "-o", "%t"], capture_output=True, text=True, env=env)
            if out.returncode == 0 and out.stdout.strip() in ("idle", "mix", "alloc"):
                return self
            time.sleep(0.5)
        log = self.root / "log" / "slurmctld.log"
        tail = log.read_text()[-400:] if log.is_file() else "(no log)"
        self.stop()
        raise Unavailable(f"the SLURM node did not come up within {timeout_s:.0f} s (sinfo: "
                          f"{out.stdout.strip() or out.stderr.strip()!r}); slurmctld.log ends: {tail!r}")

    def _start_munge(self) -> None:
        munge = self.root / "munge"
        key = munge / "munge.key"
        if not key.is_file():
            key.write_bytes(os.urandom(128))
        key.chmod(0o600)
        munge.chmod(0o700)
        self._daemon([_which("munged"), "--force", f"--key-file={key}", f"--socket={munge / 'munge.socket'}",
                      f"--pid-file={munge / 'munged.pid'}", f"--log-file={munge / 'munged.log'}",
                      f"--seed-file={munge / 'munged.seed'}"], dict(os.environ))

    def _daemon(self, argv: list, env: dict) -> None:
        proc = subprocess.run([str(a) for a in argv], capture_output=True, text=True, env=env, timeout=60)
        if proc.returncode != 0:
            self.stop()
            raise Unavailable(f"{Path(str(argv[0])).name} did not start (exit {proc.returncode}): "
                              f"{(proc.stderr or proc.stdout).strip()[:300]}")

    def stop(self) -> None:
        """Cancel every job, then end the daemons (slurmd first) and wait until they are gone."""
        env = {**os.environ, **self.env}
        if (self.root / "slurmctld.pid").is_file() and _which("scancel"):
            with contextlib.suppress(Exception):
                subprocess.run([_which("scancel"), "--full", "--partition", PARTITION], env=env, timeout=15,
                               capture_output=True)
        for pidfile in (self.root / "slurmd.pid", self.root / "slurmctld.pid", self.root / "munge" / "munged.pid"):
            pid = _read_pid(pidfile)
            if pid is None:
                continue
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGTERM)
            deadline = time.monotonic() + 15
            while _alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
            if _alive(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            with contextlib.suppress(FileNotFoundError):
                pidfile.unlink()

    # -- for tests ------------------------------------------------------------------------------------
    def squeue(self) -> list[tuple[str, str, str]]:
        """(job id, state, name) of the jobs SLURM still knows, finished ones included (MinJobAge)."""
        out = subprocess.run([_which("squeue"), "-h", "-t", "all", "-o", "%i|%T|%j"], capture_output=True,
                             text=True, env={**os.environ, **self.env}, timeout=30, check=True).stdout
        return [tuple(line.split("|", 2)) for line in out.splitlines() if line.strip()]  # type: ignore[misc]

    def scancel(self, job_id: str) -> None:
        subprocess.run([_which("scancel"), job_id], env={**os.environ, **self.env}, timeout=30, check=True)


def _read_pid(path: Path) -> int | None:
    with contextlib.suppress(OSError, ValueError):
        return int(path.read_text().split()[0])
    return None


def _alive(pid: int) -> bool:
    from pairedgta.tracking.store import process_alive

    if not process_alive(pid, ""):
        return False
    with contextlib.suppress(OSError, IndexError):  # a zombie of ours is gone for our purposes
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][:1] != "Z"
    return True


@contextlib.contextmanager
def cluster(root: Path) -> Iterator[Cluster]:
    c = Cluster(root).start()
    try:
        yield c
    finally:
        c.stop()


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in ("start", "stop"):
        print("usage: python -m pairedgta.testing.slurm start|stop DIR", file=sys.stderr)
        return 2
    c = Cluster(Path(argv[1]))
    if argv[0] == "stop":
        c.stop()
        return 0
    try:
        c.start()
    except Unavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"export SLURM_CONF={c.conf}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
