"""Shared fixtures. Helpers that tests import live in pairedgta.testing (tests import no test module)."""
from __future__ import annotations

import logging
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


@pytest.fixture(autouse=True)
def _torch_threads_put_back():
    """Each test leaves torch's intra-op thread count as it found it: a test that sets it (a training step
    on two threads, a check at 1 and 2 threads) no longer hands its count to every later test of its worker.
    Two OpenMP threads a worker, beside the other worker and the CLI runs on 2 cores, spin while they wait
    for each other: the tests after such a test spent several times their CPU (the detector formats test
    35 s against 4 s on its own)."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    yield
    torch = sys.modules.get("torch")
    if torch is None:
        return
    if before is None:  # first imported by this test: the count a fresh import gives (OMP_NUM_THREADS above)
        before = int(os.environ.get("OMP_NUM_THREADS") or 0) or torch.get_num_threads()
    if torch.get_num_threads() != before:
        torch.set_num_threads(before)


@pytest.fixture
def short_waits(monkeypatch, caplog):
    """Every wait on a locked or absent store cut to a fraction of a second (the probe's, MLflow's busy
    timeout, pysqlite's connect timeout an alembic migration runs under, the tracker's retries), so that a
    lock held for a fraction of a second does what a minute's lock does to a real run, without the suite
    sitting out the shipped waits (tests/test_tracking.py holds those to a few seconds)."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    from pairedgta.tracking import mlflow_tracker, store

    monkeypatch.setattr(mlflow_tracker, "RETRY_DELAYS_S", (0.0,))
    monkeypatch.setattr(store, "SQLITE_WAIT_S", 0.2)
    monkeypatch.setattr(store, "BUSY_TIMEOUT_MS", 100)
    monkeypatch.setattr(store, "SERVER_WAIT_S", 0.5)

    def short(dialect, conn_rec, cargs, cparams):
        if dialect.name == "sqlite":
            cparams["timeout"] = 0.2

    event.listen(Engine, "do_connect", short)
    caplog.set_level(logging.INFO, logger="pairedgta.tracking")
    yield
    event.remove(Engine, "do_connect", short)


# The slowest modules first (seconds of one worker, measured with --durations=0): with --dist loadscope
# a module runs on one worker, so starting the long ones early lets the two workers finish together
# instead of one waiting for the last long module the other picked up late. The two cluster modules start
# first, one on each worker: they mostly wait on their jobs and servers, whose CPU time the other
# modules would otherwise compete with at the end.
SLOW_FIRST = ("test_slurm.py", "test_mlflow_server.py", "test_documented_commands.py", "test_reliability.py",
              "test_journal.py", "test_store_lock.py", "test_train_detector.py", "test_write_faults.py",
              "test_demo_model.py", "test_same_numbers_across_formats.py", "test_sharding.py", "test_cli.py",
              "test_tracking.py", "test_detection.py", "test_packaging.py", "test_night_light.py",
              "test_detector_sources.py", "test_experiments.py", "test_model_channel.py", "test_train_demo.py",
              "test_python_versions.py", "test_render_blender.py", "test_corruptions.py", "test_figures.py",
              "test_bench_evaluate.py", "test_detection_study.py", "test_source_onnx.py", "test_source_export.py",
              "test_model_report.py", "test_source_python_torchvision.py", "test_pipeline.py", "test_cityscapes_val.py",
              "test_ladders.py", "test_paper_table.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))


def session_shared_dir(tmp_path_factory, name: str) -> Path:
    """A folder of this test session that every pytest-xdist worker sees: the workers' base temp folders
    (`.../pytest-N/popen-gwK`) share their parent, which is this session's alone; without xdist, the
    session's own base temp folder. For a StageCache several modules' tests share (keyed by the config's
    hash and safe for concurrent use): the first run that needs an entry builds it, later runs of the same
    config, on either worker, are cache hits of the same files."""
    base = tmp_path_factory.getbasetemp()
    path = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / f"shared-{name}"
    path.mkdir(exist_ok=True)
    return path


@pytest.fixture
def calibration(tmp_path: Path, tmp_path_factory):
    """`+experiment=photometric_calibration` through the CLI on the main job's first `scenes` scenes at 128x64 with
    one sample: (the photometry table by condition, the checks, the plot entry's folder).

    The stage cache is shared by the session's tests (tests/test_photometry.py and tests/test_night_light.py
    run the same 8 scenes' calibration): the first run renders the Blender scenes, the other reads the same
    entries through a cache-hit run of the same CLI command."""
    import pandas as pd

    from pairedgta.testing.cli import base_overrides, run_cli

    def run(scenes: int):
        cache = session_shared_dir(tmp_path_factory, f"calibration-cache-{scenes}")
        overrides = [o for o in base_overrides(tmp_path, store=False) if not o.startswith("cache_dir=")]
        proc = run_cli(overrides + [
            f"cache_dir={cache}", "+experiment=photometric_calibration", f"generate.num_scenes={scenes}",
            "renderer.width=128", "renderer.height=64", "renderer.samples=1", "plot.figures=[photometry]",
            "plot.formats=[png]", "plot.dpi=60", "tracking.enabled=false"], tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        entry, = (cache / "plot").glob("*/photometry.csv")
        checks = pd.read_csv(entry.with_name("photometry_checks.csv"))
        return pd.read_csv(entry).set_index("condition"), checks, entry.parent

    return run
