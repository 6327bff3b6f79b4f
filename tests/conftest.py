"""Shared fixtures: compose the real config tree in-process, or run the real CLI in a subprocess."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
# tests never reach a model hub
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def base_overrides(tmp: Path) -> list[str]:
    return [
        f"cache_dir={tmp / 'cache'}",
        f"tracking.uri=sqlite:///{tmp / 'mlflow.db'}",
    ]


def fast_overrides(tmp: Path) -> list[str]:
    """A tiny, quick pipeline: synthetic backend, tiny models, 3 scenes of 64x32, 3 conditions."""
    return base_overrides(tmp) + [
        "renderer=synthetic",
        "region=synthetic_street",
        "model=tiny_segformer",
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


def run_cli(args: list[str], cwd: Path, env_extra: dict | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "PYTHONWARNINGS": "ignore"}
    env.update(env_extra or {})
    return subprocess.run(
        [sys.executable, "-m", "pairedgta", *args, f"hydra.run.dir={cwd / 'run'}", f"hydra.sweep.dir={cwd / 'multirun'}"],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout,
    )


@pytest.fixture
def tmp(tmp_path: Path) -> Path:
    return tmp_path
