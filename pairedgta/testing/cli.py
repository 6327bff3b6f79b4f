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


def base_overrides(tmp: Path) -> list[str]:
    return [f"cache_dir={tmp / 'cache'}", f"tracking.uri=sqlite:///{tmp / 'mlflow.db'}"]


def fast_overrides(tmp: Path) -> list[str]:
    """A tiny, quick pipeline: synthetic backend, tiny models, 3 scenes of 64x32, 3 conditions."""
    return base_overrides(tmp) + [
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
    ]


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
    """Hydra's app entry in this process, with argv, cwd, stdout/stderr, logging and Hydra's global
    state set up as a fresh `python -m pairedgta` would have them, and put back afterwards."""
    import contextlib
    import io
    import logging
    import warnings

    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    from pairedgta.__main__ import cli

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved_handlers, saved_level = list(root.handlers), root.level
    saved_argv, saved_cwd = list(sys.argv), os.getcwd()
    code = 0
    GlobalHydra.instance().clear()
    try:
        os.chdir(cwd)
        sys.argv = ["pairedgta", *argv]
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
        GlobalHydra.instance().clear()
        HydraConfig.instance().cfg = None  # a later compose() in this process is not "inside a Hydra job"
    return subprocess.CompletedProcess(["pairedgta", *argv], code, out.getvalue(), err.getvalue())
