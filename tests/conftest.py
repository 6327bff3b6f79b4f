"""Shared fixtures. Helpers that tests import live in pairedgta.testing (tests import no test module)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# tests never reach a model hub
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# pytest-xdist runs one worker per core: a worker (and the CLI runs it starts) on one BLAS/OpenMP thread
# keeps two workers from each spinning two threads on two cores
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# The suite starts dozens of interpreters (CLI runs, SLURM jobs, tracking children) besides the xdist
# workers, which each rewrite every test module's asserts: where the environment sets
# PYTHONDONTWRITEBYTECODE, every one of them compiled pairedgta and the tests from source again (4 s of
# collection per worker, 0.4 s per interpreter). The suite keeps Python's default, the usual
# __pycache__ folders (ignored by git).
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
    sys.dont_write_bytecode = False


def _parse_each_yaml_text_once() -> None:
    """Every Hydra compose re-reads and re-parses the ~30 YAML files it uses, and the suite composes the
    config many times in each worker (an in-process CLI run composes twice: Hydra's get_mode, then the
    run): composing was a fifth of the suite's CPU, loading the files almost half of that (py-spy over
    the whole suite; the bad-config battery alone went from 31.5 s to 19.9 s with this). Keyed by
    the file's text, a parse is a pure function: the first load of a text goes through OmegaConf as
    ever (a broken file's error names it as ever), later loads of the same text get a deep copy of that
    result, as independent of every other load as a fresh parse. Runs in fresh interpreters (the
    subprocess tests, SLURM jobs, the wheel) parse as a user's run does."""
    import copy

    from omegaconf import OmegaConf

    original = OmegaConf.load
    parsed: dict[str, object] = {}

    def load(file_):
        if isinstance(file_, (str, os.PathLike)) or not callable(getattr(file_, "seek", None)):
            return original(file_)
        text = file_.read()
        if isinstance(text, bytes):
            text = text.decode("utf-8")
        if text in parsed:
            return copy.deepcopy(parsed[text])
        file_.seek(0)
        cfg = original(file_)
        parsed[text] = copy.deepcopy(cfg)
        return cfg

    OmegaConf.load = staticmethod(load)


_parse_each_yaml_text_once()


@pytest.fixture
def tmp(tmp_path: Path) -> Path:
    return tmp_path


# The slowest modules first (seconds of one worker, measured with --durations=0): with --dist loadscope
# a module runs on one worker, so starting the long ones early lets the two workers finish together
# instead of one waiting for the last long module the other picked up late. The two cluster modules start
# first, one on each worker: they mostly wait on their jobs and servers, whose CPU time the other
# modules would otherwise compete with at the end.
SLOW_FIRST = ("test_slurm.py", "test_mlflow_server.py", "test_reliability.py", "test_documented_commands.py",
              "test_journal.py", "test_write_faults.py", "test_store_lock.py", "test_cli.py", "test_demo_model.py", "test_night_light.py", "test_tracking.py",
              "test_python_versions.py", "test_train_demo.py", "test_packaging.py", "test_sharding.py",
              "test_same_numbers_across_formats.py", "test_source_onnx.py", "test_source_export.py", "test_model_report.py",
              "test_source_python_torchvision.py", "test_detection.py", "test_detector_sources.py",
              "test_experiments.py", "test_pipeline.py", "test_cityscapes_val.py", "test_ladders.py",
              "test_paper_table.py", "test_render_blender.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))


@pytest.fixture
def calibration(tmp_path: Path):
    """`+experiment=photometric_calibration` through the CLI on the main job's first `scenes` scenes at 128x64 with
    one sample: (the photometry table by condition, the checks, the plot entry's folder)."""
    import pandas as pd

    from pairedgta.testing.cli import base_overrides, run_cli

    def run(scenes: int):
        proc = run_cli(base_overrides(tmp_path) + [
            "+experiment=photometric_calibration", f"generate.num_scenes={scenes}", "renderer.width=128",
            "renderer.height=64", "renderer.samples=1", "plot.figures=[photometry]", "plot.formats=[png]",
            "plot.dpi=60", "tracking.enabled=false"], tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        entry, = (tmp_path / "cache" / "plot").glob("*/photometry.csv")
        checks = pd.read_csv(entry.with_name("photometry_checks.csv"))
        return pd.read_csv(entry).set_index("condition"), checks, entry.parent

    return run
