"""A real MLflow tracking server on loopback for the tests, with a PostgreSQL database behind it where
Debian's `postgresql` is installed (the set-up a group shares between concurrent jobs) and an SQLite
file behind it otherwise. Everything lives under one folder and stops with `stop()`.

    with mlflow_server(tmp) as server:
        run(["tracking.uri=" + server.uri, ...])
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Iterator

PG_BIN = Path("/usr/lib/postgresql")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def postgres_bin() -> Path | None:
    """The newest Debian PostgreSQL server binaries, where installed (and a driver to reach them)."""
    if importlib.util.find_spec("psycopg2") is None:
        return None
    versions = sorted((p for p in PG_BIN.glob("*/bin") if (p / "initdb").is_file()),
                      key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0)
    return versions[-1] if versions else None


class Postgres:
    """A throw-away cluster: initdb in `root`, listening on a unix socket in `root` only (no TCP port)."""

    def __init__(self, root: Path, bin_dir: Path) -> None:
        self.root, self.bin = Path(root), bin_dir
        self.data = self.root / "data"
        self.port = _free_port()
        self.user = "postgres" if os.geteuid() == 0 else pwd.getpwuid(os.getuid()).pw_name

    def _as_owner(self, argv: list[str]) -> list[str]:
        # the server refuses to run as root: as root, run it as Debian's postgres user
        return ["runuser", "-u", "postgres", "--", *argv] if os.geteuid() == 0 else argv

    def start(self) -> "Postgres":
        self.root.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(self.root, "postgres", "postgres")
            for parent in self.root.parents:  # the postgres user must reach its folder
                if parent == Path("/"):
                    break
                parent.chmod(parent.stat().st_mode | 0o001)
        subprocess.run(self._as_owner([str(self.bin / "initdb"), "-D", str(self.data), "-A", "trust", "-U",
                                       self.user, "--no-sync"]), check=True, capture_output=True, timeout=120)
        subprocess.run(self._as_owner([str(self.bin / "pg_ctl"), "-D", str(self.data), "-l",
                                       str(self.root / "postgres.log"), "-w", "-o",
                                       f"-k {self.root} -p {self.port} -c listen_addresses='' -c fsync=off",
                                       "start"]), check=True, capture_output=True, timeout=120)
        subprocess.run(self._as_owner([str(self.bin / "createdb"), "-h", str(self.root), "-p", str(self.port),
                                       "-U", self.user, "mlflow"]), check=True, capture_output=True, timeout=60)
        return self

    @property
    def uri(self) -> str:
        return f"postgresql+psycopg2://{self.user}@/mlflow?host={self.root}&port={self.port}"

    def stop(self) -> None:
        if (self.data / "postmaster.pid").is_file():
            subprocess.run(self._as_owner([str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "fast", "-w",
                                           "stop"]), capture_output=True, timeout=60)


class Server:
    def __init__(self, root: Path, backend: str = "auto") -> None:
        self.root = Path(root).resolve()
        self.port = _free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.postgres: Postgres | None = None
        bin_dir = postgres_bin() if backend in ("auto", "postgresql") else None
        if backend == "postgresql" and bin_dir is None:
            raise RuntimeError("PostgreSQL is not installed (apt-get install postgresql; pip install psycopg2-binary)")
        self.backend = "postgresql" if bin_dir is not None else "sqlite"
        self._bin = bin_dir

    def start(self, timeout_s: float = 120.0) -> "Server":
        self.root.mkdir(parents=True, exist_ok=True)
        if self._bin is not None:
            self.postgres = Postgres(self.root / "postgres", self._bin).start()
            store = self.postgres.uri
        else:
            store = f"sqlite:///{self.root / 'server.db'}"
        log = open(self.root / "server.log", "wb")
        # no job runner (a huey consumer and its five workers, each importing MLflow: seconds of the suite's
        # two cores) -- pairedgta submits no server-side jobs
        env = {**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true", "PYTHONWARNINGS": "ignore",
               "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", store,
             "--artifacts-destination", str(self.root / "artifacts"), "--host", "127.0.0.1",
             "--port", str(self.port), "--workers", "1"],
            stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
            with contextlib.suppress(OSError):
                with urllib.request.urlopen(f"{self.uri}/health", timeout=2) as reply:
                    if reply.status == 200:
                        return self
            time.sleep(0.3)
        tail = (self.root / "server.log").read_text(errors="replace")[-800:]
        self.stop()
        raise RuntimeError(f"mlflow server did not answer on {self.uri} within {timeout_s:.0f} s: {tail}")

    def stop(self) -> None:
        """The server's whole process group at once: what it stored is thrown away with its folder, so a graceful
        shutdown (uvicorn draining connections, 5 s on the 2-core machine) would buy nothing."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        if self.postgres is not None:
            self.postgres.stop()


@contextlib.contextmanager
def mlflow_server(root: Path, backend: str = "auto") -> Iterator[Server]:
    server = Server(root, backend).start()
    try:
        yield server
    finally:
        server.stop()
