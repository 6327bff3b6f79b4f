"""The worked example of docs/scaling-out.md on a real single-node SLURM cluster (munge, slurmctld and slurmd started by
the fixture, `pairedgta/testing/slurm.py`): generate in 2 SLURM shards with the embedded Blender renderer,
one shard cancelled with `scancel` mid-render and resubmitted, pseudo-labels in one job, evaluation in 2
SLURM shards, then the unsharded run that merges; the results are byte-identical to one local run."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pairedgta.testing.cli import OFFLINE, run_cli
from pairedgta.testing.slurm import Cluster, Unavailable

pytestmark = [pytest.mark.cluster, pytest.mark.slow]

# (an in-project tiny model as the model and the reference: the jobs' fresh interpreters import no transformers)
DATA = ["generate.num_scenes=4", "renderer.width=64", "renderer.height=32", "renderer.threads=1",
        "conditions.only=[Day-EXTRASUNNY,Night-RAIN]", "model=tiny_ddrnet",
        "reference_model=tiny_ddrnet", "metric.bootstrap.resamples=20", "plot.figures=[xi_models]",
        "plot.formats=[png]", "plot.dpi=50", "threads=1", "tracking.enabled=false"]
SLURM = ["hydra/launcher=slurm", "hydra.launcher.partition=debug", "hydra.launcher.gpus_per_node=0",
         "hydra.launcher.cpus_per_task=1", "hydra.launcher.mem_gb=1", "hydra.launcher.timeout_min=20"]


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    try:
        cluster = Cluster(tmp_path_factory.mktemp("slurm")).start()
    except Unavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the SLURM tests: {exc}")
        pytest.skip(f"no SLURM cluster here: {exc}")
    yield cluster
    cluster.stop()


def _sweep(args: list[str], cwd: Path, slurm: Cluster, sweep: str) -> subprocess.Popen:
    env = {**os.environ, **OFFLINE, **slurm.env, "PYTHONWARNINGS": "ignore"}
    return subprocess.Popen([sys.executable, "-m", "pairedgta", "-m", *SLURM, *args,
                             f"hydra.sweep.dir={cwd / sweep}"], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str]:
    out, _ = proc.communicate(timeout=timeout)
    return proc.returncode, out


def _entry(cache: Path, stage: str) -> Path:
    entries = [p for p in (cache / stage).glob("[!.]*") if (p / "manifest.json").is_file()]
    assert len(entries) == 1, entries
    return entries[0]


def _files(entry: Path, pattern: str) -> dict[str, bytes]:
    return {p.relative_to(entry).as_posix(): p.read_bytes() for p in sorted(entry.rglob(pattern)) if p.is_file()}


def test_the_worked_example_through_slurm_matches_one_local_run(slurm, tmp_path):
    local, cluster = tmp_path / "local", tmp_path / "cluster"
    local.mkdir(), cluster.mkdir()
    cache = cluster / "cache"
    S = DATA + [f"cache_dir={cache}"]

    # 1. render: 2 SLURM shards; shard 0 is cancelled while it renders its second scene
    gen = _sweep(S + ["stages=[generate]", "generate.num_shards=2", "generate.shard=range(2)"], cluster, slurm, "gen")
    scenes = None
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and gen.poll() is None:
        partial = next(iter((cache / "generate").glob(".partial-*")), None) if (cache / "generate").is_dir() else None
        if partial is not None:
            scenes = partial / "scenes"
            done = {int(p.name) for p in scenes.glob("[0-9]*") if (p / "timings.json").is_file()}
            if any(k % 2 == 0 for k in done) and any(int(t.name.split("-")[1]) % 2 == 0 for t in scenes.glob(".tmp-*")):
                break
        time.sleep(0.05)
    else:
        pytest.fail(f"shard 0 never rendered mid-way: {_finish(gen)[1][-3000:]}")
    job = next(j for j, state, _ in slurm.squeue() if j.endswith("_0") and state == "RUNNING")
    slurm.scancel(job)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(j == job and state == "CANCELLED" for j, state, _ in slurm.squeue()):
        time.sleep(0.2)
    kept = {int(p.name) for p in scenes.glob("[0-9]*") if (p / "timings.json").is_file() and int(p.name) % 2 == 0}
    assert kept and kept != {0, 2}, kept  # shard 0 kept what it had finished, and no more

    # ... resubmitted at once (while the first sweep waits out submitit's grace for a result file that a
    # cancelled job never writes), it renders only what is missing
    again = _sweep(S + ["stages=[generate]", "generate.num_shards=2", "generate.shard=0"], cluster, slurm, "gen-again")
    code, out = _finish(again)
    assert code == 0, out[-3000:]
    log = (cluster / "gen-again" / "0" / "pairedgta.log").read_text()
    assert f"resuming, {len(kept)} of 2 scenes already rendered" in log, log[-2000:]
    assert log.rstrip().splitlines()[-1].split(" - ", 1)[1].startswith("results: "), "the job's log ends with its results"

    # 2. pseudo-labels in one job (submitted while the first sweep still waits out its grace), then 2 SLURM
    # jobs evaluate half of the groups each
    pl = _sweep(S + ["stages=[pseudolabel]"], cluster, slurm, "pl")
    # ... and while SLURM runs it, the same config in one local run (this process: the job is another)
    proc = run_cli(DATA + [f"cache_dir={local / 'cache'}"], local)
    assert proc.returncode == 0, proc.stderr[-3000:]
    code, out = _finish(gen)
    assert code != 0 and "CANCELLED" in out, out[-3000:]  # the sweep says the job was cancelled, and does not hang
    assert "Bypassing sacct" not in out and out.count("SLURM accounting is off") == 1, out[-3000:]
    code, out = _finish(pl)
    assert code == 0, out[-3000:]
    code, out = _finish(_sweep(S + ["stages=[evaluate]", "evaluate.num_shards=2", "evaluate.shard=range(2)"],
                               cluster, slurm, "eval"))
    assert code == 0, out[-3000:]
    sharded = _entry(cache, "evaluate")  # the shard that ends last merges the partial sums into the entry
    assert not list((cache / "evaluate").glob(".parts-*"))

    # 3. the unsharded run merges and plots; the local run of the same config gave the same bytes
    proc = run_cli(S, cluster)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"evaluate [tiny_ddrnet]: cache hit {sharded}" in proc.stdout + proc.stderr
    a, b = _entry(local / "cache", "generate"), _entry(cache, "generate")
    assert a.name == b.name
    images = _files(a, "*.png")
    assert len(images) >= 4 * 2 * 2 and images == _files(b, "*.png")  # images, transmittance, labels, instances
    a, b = _entry(local / "cache", "evaluate"), _entry(cache, "evaluate")
    assert a.name == b.name
    for name in ("summary.json", "xi.csv", "pixel_agreement.csv", "gt_iou.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert json.loads((a / "summary.json").read_text())


def test_a_failing_job_shows_its_one_line_error_in_the_sweep(slurm, tmp_path):
    code, out = _finish(_sweep(DATA + [f"cache_dir={tmp_path / 'cache'}", "stages=[generate]", "generate.num_shards=2",
                                       "generate.shard=3"], tmp_path, slurm, "bad"))
    assert code != 0
    lines = [line for line in out.splitlines() if line.startswith("error: job #0")]
    assert len(lines) == 1 and "generate.shard=3 is outside 0..1" in lines[0], out[-3000:]
    assert "Traceback" not in out and "Bypassing sacct" not in out, out[-3000:]
