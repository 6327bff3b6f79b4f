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
            multirun: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, **OFFLINE, "PYTHONWARNINGS": "ignore"}
    env.update(env_extra or {})
    cmd = [sys.executable, "-m", "pairedgta", *(["-m"] if multirun else []), *args,
           f"hydra.run.dir={cwd / 'run'}", f"hydra.sweep.dir={cwd / 'multirun'}"]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
