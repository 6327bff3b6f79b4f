"""Compose the project's real config tree in-process, or run the real CLI in a subprocess, as a user would."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pairedgta.configs import CONFIG_DIR, CONFIG_MODULE

CONF = CONFIG_DIR
OFFLINE = {"HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}


def compose_cfg(overrides: list[str]):
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


_TEMPLATE: dict[str, Path] = {}


def mlflow_store(db: Path) -> str:
    """`sqlite:///<db>`, a store with MLflow's empty schema already in it (when `db` does not exist yet
    and its folder does: a missing or broken folder is left for the product to meet).

    Creating a store runs MLflow's ~50 schema migrations, 2.5 s on the 2-core machine: a test process
    pays that once, for a template it copies, instead of once per test. Tests of store creation itself
    pass their own URI."""
    import atexit
    import shutil
    import tempfile

    if db.parent.is_dir() and not db.exists():
        if "db" not in _TEMPLATE:
            from mlflow.tracking import MlflowClient

            folder = Path(tempfile.mkdtemp(prefix="pgta-mlflow-template-"))
            atexit.register(shutil.rmtree, folder, True)
            template = folder / "mlflow.db"
            MlflowClient(tracking_uri=f"sqlite:///{template}").search_experiments()
            _TEMPLATE["db"] = template
        shutil.copyfile(_TEMPLATE["db"], db)
    return f"sqlite:///{db}"


def base_overrides(tmp: Path, store: bool = True) -> list[str]:
    """The cache and the MLflow store under `tmp`; the store seeded (see `mlflow_store`) unless `store=False`."""
    uri = mlflow_store(tmp / "mlflow.db") if store else f"sqlite:///{tmp / 'mlflow.db'}"
    return [f"cache_dir={tmp / 'cache'}", f"tracking.uri={uri}"]


def fast_overrides(tmp: Path) -> list[str]:
    """A tiny, quick pipeline: synthetic backend, tiny models, 3 scenes of 64x32, 3 conditions."""
    return base_overrides(tmp, store=False) + [
        "renderer=synthetic",
        "region=synthetic_street",
        "model=tiny_segformer",
        "models=null",  # just `model` (the default list is the shipped zoo)
        "reference_model=tiny_segformer",
        "generate.num_scenes=3",
        "renderer.width=64",
        "renderer.height=32",
        "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]",
        "metric.bootstrap.resamples=50",
        "plot.formats=[png]",
        "plot.dpi=60",
        "tracking.enabled=false",
        "threads=1",  # pytest-xdist runs a worker per core: two workers of two inference threads would contend
    ]


REPORT_POPULATION = ("tiny_ddrnet", "tiny_pidnet")


def report_overrides(tmp: Path) -> list[str]:
    """`fast_overrides` as `+experiment=model_report` of the model chosen after them, placed against two tiny zoo
    graphs: a source's test runs it through the CLI to its report page."""
    return [o for o in fast_overrides(tmp) if not o.startswith("model=")] + [
        "+experiment=model_report", f"report.population=[{','.join(REPORT_POPULATION)}]", "report.worst_cases=1"]


def report_page(proc: subprocess.CompletedProcess, model: str) -> Path:
    """The model report's markdown a run wrote for `model`, from the line the run prints (the page beside it)."""
    import re

    found = re.search(rf"model report of {re.escape(model)} \(model_report.md beside it\): (\S+)", proc.stdout + proc.stderr)
    assert found, (proc.stdout + proc.stderr)[-3000:]
    md = Path(found.group(1)).with_suffix(".md")
    assert md.is_file() and md.read_text().startswith(f"# Model report: {model}"), md
    return md


def run_cli(args: list[str], cwd: Path, env_extra: dict | None = None, timeout: int = 600,
            multirun: bool = False, subprocess_: bool | None = None) -> subprocess.CompletedProcess:
    """`python -m pairedgta ARGS` run from `cwd`, as a CompletedProcess (returncode, stdout, stderr).

    In-process by default: the same Hydra entry point (`pairedgta.__main__.cli`) with the same argv, but
    without paying ~4 s of interpreter and import start-up per run. A subprocess where the process itself
    is under test: `env_extra` (environment read at import time), or `subprocess_=True` (the handful of
    end-to-end runs that check what only a fresh interpreter shows)."""
    extra = [*(["-m"] if multirun else []), *args, f"hydra.run.dir={cwd / 'run'}", f"hydra.sweep.dir={cwd / 'multirun'}"]
    if subprocess_ or (subprocess_ is None and env_extra):
        env = {**os.environ, **OFFLINE, "PYTHONWARNINGS": "ignore"}
        env.update(env_extra or {})
        return subprocess.run([sys.executable, "-m", "pairedgta", *extra], cwd=cwd, env=env, capture_output=True,
                              text=True, timeout=timeout)
    return _run_in_process(extra, cwd)


def _run_in_process(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    from pairedgta.__main__ import cli

    return run_app_in_process(cli, ["pairedgta", *argv], cwd)


def run_app_in_process(cli, argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """A `@hydra.main` entry (`cli`) in this process, with argv (`argv[0]` the program), cwd,
    stdout/stderr, logging and Hydra's global state set up as a fresh interpreter would have them, and
    put back afterwards (torch's thread count too, which a training script sets)."""
    import contextlib
    import io
    import logging
    import warnings

    from hydra._internal.hydra import Hydra
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved_handlers, saved_level = list(root.handlers), root.level
    saved_argv, saved_cwd = list(sys.argv), os.getcwd()
    torch = sys.modules.get("torch")
    saved_threads = torch.get_num_threads() if torch is not None else None
    code = 0
    GlobalHydra.instance().clear()
    real_get_mode = Hydra.get_mode
    Hydra.get_mode = _mode_from_overrides
    try:
        os.chdir(cwd)
        sys.argv = list(argv)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                cli()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                if exc.code is not None and not isinstance(exc.code, int):
                    print(exc.code, file=sys.stderr)
            finally:
                for h in list(root.handlers):
                    if h not in saved_handlers:
                        root.removeHandler(h)
                        h.close()
    finally:
        os.chdir(saved_cwd)
        sys.argv = saved_argv
        for h in saved_handlers:
            if h not in root.handlers:
                root.addHandler(h)
        root.setLevel(saved_level)
        Hydra.get_mode = real_get_mode
        GlobalHydra.instance().clear()
        HydraConfig.instance().cfg = None  # a later compose() in this process is not "inside a Hydra job"
        if saved_threads is not None:
            torch.set_num_threads(saved_threads)
    return subprocess.CompletedProcess(list(argv), code, out.getvalue(), err.getvalue())


def _mode_from_overrides(self, config_name, overrides):
    """Hydra's get_mode without its compose: Hydra composes the whole config once only to read `hydra.mode`
    (errors swallowed, None where unset) and then again for the run; no file of pairedgta sets `hydra.mode`
    (tests/test_config.py holds that), so only an override can. The in-process runs compose once: that first
    compose was about a quarter of each in-process run's time (documented commands: 20.7 s -> 15.1 s)."""
    from hydra.types import RunMode

    for o in overrides:
        key, _, value = o.partition("=")
        if key.lstrip("+~") == "hydra.mode" and value in RunMode.__members__:
            return RunMode[value]
    return None


def locked_sqlite(db: Path):
    """A context in which another program holds `db`'s write lock (a DB browser or a backup mid-transaction)."""
    import contextlib
    import sqlite3

    @contextlib.contextmanager
    def holding():
        holder = sqlite3.connect(db, isolation_level=None)
        holder.execute("BEGIN EXCLUSIVE")
        try:
            yield
        finally:
            holder.execute("ROLLBACK")
            holder.close()

    return holding()
