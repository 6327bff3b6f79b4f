"""Nothing lost, nothing stale, every bad input one line (issue 16), tried as a hostile user would:
failed and concurrent forced recomputes, damaged cache entries, same-size replaced inputs, missing
conditions, strict JSON, corrupt or hostile weights, pathological renderer replies, crashed and killed
runs, concurrent run folders, execution-only keys and thread counts."""
from __future__ import annotations

import json
import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from pairedgta.app import run
from pairedgta.cache import MANIFEST, StageCache
from pairedgta.conditions import build_condition_grid
from pairedgta.errors import DataError, ModelError, PairedGTAError, RendererError
from pairedgta.stages.common import Context, StageResult, run_cached
from pairedgta.testing.cli import compose_cfg, fast_overrides, mlflow_store

ROOT = Path(__file__).resolve().parents[1]

FAST3 = "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]"


def wait_until(predicate, timeout=120.0, proc: subprocess.Popen | None = None) -> bool:
    """Bounded wait on a condition (not a sleep-then-assert); stops early if `proc` exits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        if proc is not None and proc.poll() is not None:
            return bool(predicate())
        time.sleep(0.01)
    return False


def fast(tmp: Path, *extra: str) -> list[str]:
    """fast_overrides with `extra` replacing same-key entries (Hydra refuses a key given twice), and one
    figure unless `extra` names them (drawing is most of a tiny run's time; these tests read no figure)."""
    keys = {e.split("=", 1)[0] for e in extra}
    base = fast_overrides(tmp) + ["plot.figures=[xi_models]"]
    return [o for o in base if o.split("=", 1)[0] not in keys] + list(extra)


def hits(summary):
    return {(s["stage"], s["label"]): s["hit"] for s in summary["stages"]}


def entries(cache: Path, stage: str) -> list[Path]:
    d = cache / stage
    return sorted(p for p in d.iterdir() if not p.name.startswith(".") and p.is_dir()) if d.is_dir() else []


def leftovers(cache: Path) -> list[Path]:
    return sorted(p for p in cache.glob("*/.*") if p.is_dir())


@dataclass
class FnStage:
    """The smallest Stage: a name, a config to hash and a function that writes the entry."""

    name: str
    config: dict
    fn: Callable[[Path], None]
    upstream: dict = field(default_factory=dict)
    version: str = "1"
    label: str = ""
    resumable: bool = False
    result_cls: type = StageResult

    def hash_config(self) -> dict:
        return self.config

    def inputs(self) -> dict:
        return self.upstream

    def build(self, out: Path, key: str) -> None:
        self.fn(out)

    def shards(self) -> tuple[int, int]:
        return 1, 0

    def build_shard(self, key: str) -> None:
        raise AssertionError("not sharded")


def context(root: Path, stages=("evaluate",), force=()) -> Context:
    grid = build_condition_grid(OmegaConf.to_container(compose_cfg([]).conditions))
    return Context(cfg={}, grid=grid, cache=StageCache(root), stages=list(stages), force=set(force))


# --------------------------------------------------------------------------- force= never loses data


def test_failed_forced_recompute_keeps_the_previous_result(tmp_path):
    def good(out: Path):
        (out / "xi.csv").write_text("v1")

    def failing(out: Path):
        (out / "xi.csv").write_text("half")
        raise RendererError("GTA server down")

    first = run_cached(context(tmp_path), FnStage("evaluate", {"a": 1}, good))
    with pytest.raises(RendererError):
        run_cached(context(tmp_path, force={"evaluate"}), FnStage("evaluate", {"a": 1}, failing))
    assert (first.path / "xi.csv").read_text() == "v1"
    assert StageCache(tmp_path).is_hit("evaluate", first.key)
    assert leftovers(tmp_path) == []  # the failed attempt's folder is gone

    def better(out: Path):
        (out / "xi.csv").write_text("v2")

    again = run_cached(context(tmp_path, force={"evaluate"}), FnStage("evaluate", {"a": 1}, better))
    assert again.path == first.path and (again.path / "xi.csv").read_text() == "v2"
    assert leftovers(tmp_path) == [] and [p.name for p in entries(tmp_path, "evaluate")] == [first.key]


def test_stage_cache_lists_finished_entries_with_their_manifests(tmp_path):
    """What evaluate's search for other models' evaluations reads: finished entries only, unreadable skipped."""
    ctx = context(tmp_path)
    a = run_cached(ctx, FnStage("evaluate", {"a": 1}, lambda out: (out / "xi.csv").write_text("a"), {"in": "x"}))
    b = run_cached(ctx, FnStage("evaluate", {"a": 2}, lambda out: (out / "xi.csv").write_text("b"), {"in": "x"}))
    crashed = tmp_path / "evaluate" / f".tmp-{a.key}-1-0000abcd"  # a crashed build, manifest already written
    crashed.mkdir()
    (crashed / MANIFEST).write_text((a.path / MANIFEST).read_text())
    broken = tmp_path / "evaluate" / "0123456789abcdef"
    broken.mkdir()
    (broken / MANIFEST).write_text("{")
    found = StageCache(tmp_path).entries("evaluate")
    assert [e.key for e in found] == sorted([a.key, b.key])
    assert {e.key: (e.path, e.manifest["config"], e.manifest["inputs"]) for e in found} == {
        a.key: (a.path, {"a": 1}, {"in": "x"}), b.key: (b.path, {"a": 2}, {"in": "x"})}
    assert all(e.mtime == (e.path / MANIFEST).stat().st_mtime for e in found)
    assert StageCache(tmp_path).entries("pseudolabel") == []


def test_forced_recompute_waits_for_a_job_still_reading_the_old_result(tmp_path):
    def old(out: Path):
        (out / "a.png").write_text("old")

    run_cached(context(tmp_path, stages=("generate",)), FnStage("generate", {}, old))
    reader = context(tmp_path, stages=("evaluate",))  # another job, evaluating the cached dataset
    used = run_cached(reader, FnStage("generate", {}, lambda out: None))
    assert used.hit
    built = threading.Event()
    errors: list[BaseException] = []

    def rebuild(out: Path):
        (out / "a.png").write_text("new")
        built.set()

    def forced_job():
        try:
            run_cached(context(tmp_path, stages=("generate",), force={"generate"}), FnStage("generate", {}, rebuild))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=forced_job)
    t.start()
    assert built.wait(30)
    # the new result is complete beside the old one, but the reader still sees the old, whole
    assert wait_until(lambda: any((p / MANIFEST).is_file() for p in (tmp_path / "generate").glob(".tmp-*")), 30)
    t.join(0.2)
    assert t.is_alive() and (used.path / "a.png").read_text() == "old"
    reader.cache.release()  # the reading job ends
    t.join(30)
    assert not t.is_alive() and not errors
    assert (used.path / "a.png").read_text() == "new" and leftovers(tmp_path) == []


# --------------------------------------------------------------------------- nothing stale


@pytest.mark.slow
def test_damaged_cache_entries_are_rebuilt_and_the_log_says_why(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    base = fast(tmp_path, "models=[tiny_segformer]")  # one figure: the plot stage runs, and reads the evaluation
    run(compose_cfg(base))
    cache = tmp_path / "cache"
    evaluation = entries(cache, "evaluate")[0]
    (evaluation / "xi.csv").unlink()
    again = hits(run(compose_cfg(base)))
    assert not again[("evaluate", "[tiny_segformer]")] and again[("pseudolabel", "[tiny_segformer]")]
    assert "is damaged (xi.csv is missing); rebuilding it" in caplog.text
    assert (evaluation / "xi.csv").is_file()

    # same size, other bytes: a content change the size check cannot see
    scene = entries(cache, "generate")[0] / "scenes" / "00001" / "Night-EXTRASUNNY.png"
    data = bytearray(scene.read_bytes())
    data[-20] ^= 0xFF
    scene.write_bytes(bytes(data))
    caplog.clear()
    after = hits(run(compose_cfg(base)))
    assert not after[("generate", "")]
    assert "scenes/00001/Night-EXTRASUNNY.png changed content" in caplog.text

    # a stage not run this time cannot be rebuilt: one line naming the damage and the fix
    (evaluation / "frame_counts.csv").unlink()
    with pytest.raises(PairedGTAError, match=r"damaged \(frame_counts\.csv is missing\).*stages=\[evaluate"):
        run(compose_cfg(base + ["stages=[plot]"]))


@pytest.mark.slow
def test_cache_verify_content_sees_an_edit_that_kept_size_and_mtime(tmp_path, caplog):
    """As in DVC, the default trusts a file whose size and mtime match the memo; cache.verify=content
    re-hashes every file of an entry on every hit and so sees the edit."""
    caplog.set_level(logging.INFO)
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer]", "stages=[generate]"]
    run(compose_cfg(base))
    scene = entries(tmp_path / "cache", "generate")[0] / "scenes" / "00001" / "Day-RAIN.png"
    st = scene.stat()
    data = bytearray(scene.read_bytes())
    data[-20] ^= 0xFF
    scene.write_bytes(bytes(data))
    os.utime(scene, ns=(st.st_atime_ns, st.st_mtime_ns))  # the edit keeps size and mtime
    assert hits(run(compose_cfg(base)))[("generate", "")]  # stat: the memo's hash is trusted
    caplog.clear()
    assert not hits(run(compose_cfg(base + ["cache.verify=content"])))[("generate", "")]
    assert "scenes/00001/Day-RAIN.png changed content" in caplog.text


@pytest.mark.slow
def test_a_collected_evaluation_missing_a_file_is_an_error_not_a_missing_model(tmp_path):
    base = fast_overrides(tmp_path)
    run(compose_cfg(base + ["models=[tiny_segformer]", "stages=[generate,pseudolabel,evaluate]"]))
    run(compose_cfg(base + ["models=[tiny_mask2former]", "stages=[generate,pseudolabel,evaluate]"]))
    cache = tmp_path / "cache"
    other = next(e for e in entries(cache, "evaluate")
                 if json.loads((e / MANIFEST).read_text())["config"]["model"]["name"] == "tiny_mask2former")
    (other / "frame_counts.csv").unlink()
    with pytest.raises(DataError, match=r"frame_counts\.csv is missing.*force=\[evaluate\]"):
        run(compose_cfg(base + ["models=[tiny_segformer]", "plot.collect_cached=true", "plot.figures=[ranking]"]))


def write_release_same_size(root: Path, seed: int, locs=(1, 2), conditions=("Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY"),
                            missing=()):
    """Uncompressed PNGs: every file's size depends on the image size only, not on the content."""
    rng = np.random.default_rng(seed)
    for loc in locs:
        for c in conditions:
            if (loc, c) in missing:
                continue
            time_, weather = c.split("-")
            (root / time_).mkdir(parents=True, exist_ok=True)
            arr = rng.integers(0, 255, size=(32, 64, 3), dtype=np.uint8)
            Image.fromarray(arr).save(root / time_ / f"{loc}_{time_}_{weather}.png", compress_level=0)


def release_overrides(tmp_path: Path, root: Path) -> list[str]:
    return fast_overrides(tmp_path) + ["dataset=paired_gta", f"dataset.root={root}", "models=[tiny_segformer]",
                                       "stages=[pseudolabel,evaluate]"]


@pytest.mark.slow
def test_same_size_replaced_dataset_is_not_a_cache_hit(tmp_path):
    root = tmp_path / "release"
    write_release_same_size(root, seed=0)
    before = {p: p.stat().st_size for p in root.rglob("*.png")}
    args = release_overrides(tmp_path, root)
    assert not any(hits(run(compose_cfg(args))).values())
    assert all(hits(run(compose_cfg(args))).values())
    write_release_same_size(root, seed=1)  # every image replaced, every byte size unchanged
    assert {p: p.stat().st_size for p in root.rglob("*.png")} == before
    h = hits(run(compose_cfg(args)))
    assert not h[("pseudolabel", "[tiny_segformer]")] and not h[("evaluate", "[tiny_segformer]")]


def test_dataset_content_hashes_are_memoised_on_path_size_and_mtime(tmp_path):
    from pairedgta.datasets import open_dataset
    from pairedgta.filehash import HashMemo, set_default

    root = tmp_path / "release"
    write_release_same_size(root, seed=0)
    grid = build_condition_grid(OmegaConf.to_container(compose_cfg([FAST3]).conditions))
    ds = open_dataset({"kind": "paired_gta", "name": "paired_gta"}, grid, root=root)
    memo = set_default(tmp_path / "cache")
    first = ds.fingerprint()
    assert memo.hashed == 6
    fresh = set_default(tmp_path / "cache2")  # another memo: everything is read again
    assert ds.fingerprint() == first and fresh.hashed == 6
    memo = set_default(tmp_path / "cache")
    memo.hashed = 0
    assert ds.fingerprint() == first and memo.hashed == 0  # unchanged files are not read again
    png = root / "Day" / "2_Day_RAIN.png"
    data = bytearray(png.read_bytes())
    data[100] ^= 1
    st = png.stat()
    png.write_bytes(bytes(data))
    # a later replacement has a later mtime; make sure even on a coarse-mtime file system
    os.utime(png, ns=(st.st_atime_ns, max(png.stat().st_mtime_ns, st.st_mtime_ns + 1_000_000_000)))
    assert ds.fingerprint() != first and memo.hashed == 1
    assert HashMemo(tmp_path / "cache" / ".hash-memo.sqlite").sha256(png) == __import__("hashlib").sha256(png.read_bytes()).hexdigest()


@pytest.mark.slow
def test_a_group_missing_a_condition_is_counted_and_reported(tmp_path, caplog):
    root = tmp_path / "release"
    write_release_same_size(root, seed=0, locs=(1, 2, 3), missing={(2, "Night-EXTRASUNNY")})
    s = run(compose_cfg(release_overrides(tmp_path, root)))
    summary = json.loads((Path(s["evaluate"]["tiny_segformer"]) / "summary.json").read_text())
    assert summary["groups_per_condition"] == {"Day-EXTRASUNNY": 3, "Day-RAIN": 3, "Night-EXTRASUNNY": 2}
    assert summary["groups_without_clean"] == 0
    assert "Day-EXTRASUNNY 3, Day-RAIN 3, Night-EXTRASUNNY 2" in caplog.text


# --------------------------------------------------------------------------- strict JSON


@pytest.mark.slow
def test_every_json_written_is_strict(tmp_path):
    from pairedgta.jsonio import dumps

    assert json.loads(dumps({"a": float("nan"), "b": [float("inf"), np.float32(0.5)], "c": np.int64(3)})) == {
        "a": None, "b": [None, 0.5], "c": 3}
    # tau=1: no pseudo-label pixel survives, so agreement and several xi are NaN in the numbers
    run(compose_cfg(fast(tmp_path, "models=[tiny_segformer]", "pseudolabel.tau=1.0", "metric.bootstrap.resamples=0")))
    files = list((tmp_path / "cache").rglob("*.json"))
    assert len(files) >= 10

    def refuse(token):
        raise ValueError(f"non-strict JSON constant {token}")

    for f in files:
        json.loads(f.read_text(), parse_constant=refuse)
    summary = json.loads(next((tmp_path / "cache" / "evaluate").glob("*/summary.json")).read_text())
    assert None in summary["agreement"].values()


# --------------------------------------------------------------------------- hostile weights and replies


def test_corrupt_safetensors_and_pickled_weights_are_one_line_model_errors(tmp_path):
    from pairedgta.models import build_model

    weights = tmp_path / "weights"
    build_model("tiny_segformer").module.save_pretrained(weights)
    st = weights / "model.safetensors"
    st.write_bytes(b"\xff" * 64 + st.read_bytes()[64:])  # header length and JSON destroyed
    with pytest.raises(ModelError) as info:
        build_model("segformer_b0", path=str(weights))
    msg = str(info.value)
    assert "\n" not in msg and f"model.path={weights}" in msg and "Error" in msg

    # a pickle instead of safetensors: refused unread, and the refusal names the global
    st.unlink()
    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    torch.save({"segformer.encoder.x": Exploit()}, weights / "pytorch_model.bin")
    with pytest.raises(ModelError) as info:
        build_model("segformer_b0", path=str(weights))
    msg = str(info.value)
    assert "\n" not in msg and f"model.path={weights}" in msg
    assert not marker.exists()


def test_refused_checkpoint_shows_its_whole_reason(tmp_path):
    from pairedgta.models.checkpoint import read_state_dict

    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    path = tmp_path / "evil.pt"
    torch.save({"weight": Exploit()}, path)
    with pytest.raises(ModelError) as info:
        read_state_dict(path)
    msg = str(info.value)
    assert "posix.system" in msg and "\n" not in msg
    assert not marker.exists()


def test_deeply_nested_frame_json_is_a_renderer_error(tmp_path):
    from pairedgta.render.deepgtav import DeepGTAVRenderer
    from pairedgta.render.deepgtav_protocol import frame_nbytes
    from pairedgta.scene.descriptor import Location, SceneDescriptor

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    listener.settimeout(10.0)
    port = listener.getsockname()[1]
    nested = b"[" * 100_000 + b"]" * 100_000
    frame = b"\x00" * frame_nbytes(32, 8)

    def serve():
        for _ in range(2):  # one connection per attempt
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            with conn:
                conn.sendall(struct.pack("<I", len(frame)) + frame + struct.pack("<I", len(nested)) + nested)
                conn.settimeout(10.0)
                try:
                    while conn.recv(65536):  # until the client gives up on this connection
                        pass
                except OSError:
                    pass

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    r = DeepGTAVRenderer(width=32, height=8, port=port, transport="tcp", timeout_s=2.0, retries=1,
                         backoff_s=0.01, rate=100.0)
    with pytest.raises(RendererError) as info:
        r.prepare(SceneDescriptor("s", 1, Location(0.0, 0.0)))
    r.close()
    listener.close()
    t.join(10)
    assert "nests too deeply" in str(info.value) and "\n" not in str(info.value)


# --------------------------------------------------------------------------- crashes, kills, run folders


def cli(args: list[str], cwd: Path, run_dir: bool = True) -> subprocess.Popen:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "PYTHONWARNINGS": "ignore",
           "PYTHONPATH": str(ROOT)}
    extra = [f"hydra.run.dir={cwd / 'run'}"] if run_dir else []
    return subprocess.Popen([sys.executable, "-m", "pairedgta", *args, *extra], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def slow_args(tmp_path: Path, scenes: int = 30) -> list[str]:
    """30 scenes through demo_segformer: pseudolabel + evaluate take ~13 s on one idle core, three times
    what the run's tracking child needs to import MLflow and open its run (~4 s): a wide window to be
    caught in. (A tiny model needed 100 scenes for that window, and generating them cost twice as much.)"""
    return [f"cache_dir={tmp_path / 'cache'}", f"tracking.uri={mlflow_store(tmp_path / 'mlflow.db')}", "renderer=synthetic",
            "region=synthetic_street", "model=demo_segformer", "reference_model=demo_segformer", f"generate.num_scenes={scenes}",
            "renderer.width=256", "renderer.height=128", FAST3, "metric.bootstrap.resamples=20", "plot.formats=[png]",
            "plot.dpi=40", "name=crash"]


@pytest.fixture(scope="module")
def slow_dataset(tmp_path_factory) -> Path:
    """The dataset of `slow_args`, generated once in-process: the kill and SIGTERM tests start their
    child from a copy, so it is caught in pseudolabel/evaluate without generating the scenes each time."""
    from pairedgta.testing.cli import run_cli

    base = tmp_path_factory.mktemp("slow")
    proc = run_cli(slow_args(base) + ["stages=[generate]", "tracking.enabled=false"], base)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (entry,) = entries(base / "cache", "generate")
    return entry


def with_dataset(tmp_path: Path, dataset: Path) -> None:
    import shutil

    shutil.copytree(dataset, tmp_path / "cache" / "generate" / dataset.name)


def mlflow_runs(tmp_path: Path):
    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("crash")
    return client.search_runs([exp.experiment_id]) if exp else []


def running_with_tmp(tmp_path: Path) -> bool:
    """The child is inside pseudolabel/evaluate: a temp folder exists and its MLflow run is RUNNING."""
    import sqlite3

    cache = tmp_path / "cache"
    if not list(cache.glob("evaluate/.tmp-*")) and not list(cache.glob("pseudolabel/.tmp-*")):
        return False
    try:
        with sqlite3.connect(tmp_path / "mlflow.db", timeout=1) as db:
            return db.execute("SELECT count(*) FROM runs WHERE status = 'RUNNING'").fetchone()[0] > 0
    except sqlite3.Error:  # the store is being created by the child
        return False


@pytest.mark.slow
def test_kill_9_mid_run_leaves_nothing_after_the_next_run(tmp_path, slow_dataset):
    cache = tmp_path / "cache"
    with_dataset(tmp_path, slow_dataset)
    proc = cli(slow_args(tmp_path), tmp_path)
    try:
        assert wait_until(lambda: running_with_tmp(tmp_path), 300, proc), proc.communicate()[1][-2000:]
        proc.kill()  # kill -9: no handler runs
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert leftovers(cache)

    def dead():
        return [r for r in mlflow_runs(tmp_path) if r.data.tags.get("pairedgta.pid") == str(proc.pid)]

    # its tracking child reads end-of-file and ends the dead process's runs KILLED at once (a run whose
    # child died too is ended by the next run: tests/test_tracking.py); a model's nested run may have finished
    assert wait_until(lambda: dead() and all(r.info.status != "RUNNING" for r in dead()), 60)
    assert [r.info.status for r in dead() if "mlflow.parentRunId" not in r.data.tags] == ["KILLED"]
    assert {r.info.status for r in dead()} <= {"KILLED", "FINISHED"}
    nxt = cli(slow_args(tmp_path) + ["stages=[generate]"], tmp_path)
    out, err = nxt.communicate(timeout=300)
    assert nxt.returncode == 0, err[-2000:]
    assert leftovers(cache) == []
    # the next run (it stops after generation) is recorded too, as finished
    assert [r.info.status for r in mlflow_runs(tmp_path) if r.data.tags.get("pairedgta.pid") == str(nxt.pid)] == ["FINISHED"]


@pytest.mark.slow
def test_sigterm_unwinds_marks_the_run_killed_and_keeps_finished_work(tmp_path, slow_dataset):
    cache = tmp_path / "cache"
    with_dataset(tmp_path, slow_dataset)
    proc = cli(slow_args(tmp_path), tmp_path)
    try:
        assert wait_until(lambda: running_with_tmp(tmp_path), 300, proc), proc.communicate()[1][-2000:]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "SIGTERM" in errors[0] and "Traceback" not in err
    assert [r.info.status for r in mlflow_runs(tmp_path)] == ["KILLED"]
    assert not list(cache.glob("*/.tmp-*"))
    assert len(entries(cache, "generate")) == 1  # the finished dataset is kept


@pytest.mark.slow
def test_a_crashed_generate_partial_is_removed_after_the_next_successful_run(tmp_path):
    cache = tmp_path / "cache"
    proc = cli(slow_args(tmp_path, scenes=3000) + ["stages=[generate]", "tracking.enabled=false"], tmp_path)
    try:
        assert wait_until(lambda: any(True for _ in cache.glob("generate/.partial-*/scenes/0000[0-9]")), 300, proc)
        proc.kill()
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(cache.glob("generate/.partial-*"))
    other = cli(slow_args(tmp_path, scenes=2) + ["stages=[generate]", "tracking.enabled=false"], tmp_path)
    out, err = other.communicate(timeout=300)
    assert other.returncode == 0, err[-2000:]
    assert leftovers(cache) == []
    assert "left by a crashed run" in out + err


@pytest.mark.slow
def test_concurrent_runs_get_distinct_run_folders(tmp_path):
    # both stop at once on a bad value, after Hydra made their run folders
    procs = [cli([f"cache_dir={tmp_path / 'cache'}", "plot.dpi=0", "tracking.enabled=false"], tmp_path, run_dir=False)
             for _ in range(2)]
    for p in procs:
        p.communicate(timeout=120)
        assert p.returncode == 2
    dirs = sorted((tmp_path / "outputs" / "runs").iterdir())
    assert len(dirs) == 2
    for p in procs:
        assert sum(d.name.endswith(f"_{p.pid}") for d in dirs) == 1


# --------------------------------------------------------------------------- hashes


def test_execution_only_keys_stay_out_of_the_dataset_hash():
    from pairedgta import schema
    from pairedgta.stages.generate import hash_config

    def key(extra):
        cfg = OmegaConf.to_container(compose_cfg(["renderer=deepgtav", "region=los_santos", *extra]), resolve=True)
        grid = build_condition_grid(cfg["conditions"])
        return json.dumps(hash_config(schema.parse(cfg), grid), sort_keys=True)

    base = key([])
    for extra in (["renderer.backoff_s=7"], ["renderer.retries=9"], ["renderer.timeout_s=99"],
                  ["renderer.host=10.0.0.2"], ["renderer.port=9"], ["generate.workers=3"],
                  ["generate.endpoints=[{port:1},{port:2}]"]):
        assert key(extra) == base, extra
    assert key(["renderer.width=640"]) != base and key(["renderer.settle_s=3"]) != base


@pytest.mark.slow
def test_evaluate_is_identical_at_1_and_2_torch_threads(tmp_path, monkeypatch):
    from pairedgta.models import build_model

    # precondition: this model's float reductions do depend on the thread count
    model = build_model("demo_segformer")
    x = np.random.default_rng(0).integers(0, 255, size=(3, 32, 64, 3), dtype=np.uint8)
    probs = {}
    for n in (1, 2):
        torch.set_num_threads(n)
        probs[n] = model.predict_proba(x)
    assert (probs[1] - probs[2]).abs().max() > 0

    from pairedgta.models.base import Segmenter

    seen: list[int] = []
    original = Segmenter._forward

    def spy(self, images, **kwargs):  # kwargs: what predict_maps asks of the same forward (energy=)
        seen.append(torch.get_num_threads())
        return original(self, images, **kwargs)

    monkeypatch.setattr(Segmenter, "_forward", spy)  # every forward: predict_maps, predict and predict_proba alike
    outputs = []
    for ambient in (1, 2):
        torch.set_num_threads(ambient)
        base = fast(tmp_path / str(ambient), "models=[demo_segformer]", "reference_model=demo_segformer",
                    "stages=[generate,pseudolabel,evaluate]", "threads=1")
        s = run(compose_cfg(base))
        d = Path(s["evaluate"]["demo_segformer"])
        outputs.append({n: (d / n).read_bytes() for n in ("xi.csv", "pixel_agreement.csv", "frame_counts.csv")})
        assert torch.get_num_threads() == ambient  # restored after the stage
    assert outputs[0] == outputs[1]
    assert seen and set(seen) == {1}  # inference ran on the configured `threads`, not the ambient count
    torch.set_num_threads(2)
    keyed = run(compose_cfg(fast(tmp_path / "1", "models=[demo_segformer]", "reference_model=demo_segformer",
                                 "stages=[generate,pseudolabel,evaluate]", "threads=3")))
    assert not hits(keyed)[("evaluate", "[demo_segformer]")]  # the thread count is part of the hash


@pytest.mark.slow
def test_a_full_disk_is_one_line_and_leaves_nothing_half_written(tmp_path, monkeypatch):
    """ENOSPC in the middle of rendering: one line naming the place and the fix, exit 2, no traceback,
    no temporary scene folder or file left, and the scenes finished before it are kept for the rerun."""
    import errno

    from pairedgta.stages import generate as generate_stage
    from pairedgta.testing.cli import run_cli

    real = generate_stage.save_png_atomic
    written = []

    def filling(array, path):
        if len(written) >= 26:  # the disk fills up in the third scene (3 conditions x 4 maps a scene)
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        written.append(path)
        real(array, path)

    monkeypatch.setattr(generate_stage, "save_png_atomic", filling)
    args = fast_overrides(tmp_path) + ["stages=[generate]", "generate.num_scenes=3"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    cache = tmp_path / "cache" / "generate"
    assert len(errors) == 1 and f"no space left on the disk of {cache}" in errors[0], proc.stderr  # the entry
    assert "cache_dir=/another/disk" in errors[0] and "Traceback" not in proc.stderr
    assert not list(cache.rglob(".tmp-*")) and not list(cache.rglob("*.tmp"))
    assert entries(tmp_path / "cache", "generate") == []  # no entry claims to be complete
    assert len([d for d in cache.glob(".partial-*/scenes/*") if d.is_dir()]) == 2  # finished scenes are kept
    monkeypatch.setattr(generate_stage, "save_png_atomic", real)
    assert run_cli(args, tmp_path).returncode == 0  # the rerun resumes


@pytest.mark.slow
def test_a_full_disk_without_a_file_name_still_names_the_folder(tmp_path, monkeypatch):
    """A real write() that hits ENOSPC carries no file name: the error still names the folder being
    written (the generate entry) and no temporary is left (FAILED in MLflow: tests/test_tracking.py)."""
    import errno

    from pairedgta.testing.cli import run_cli

    real = Path.write_text

    def full(self, *args, **kwargs):
        if "/generate/" in str(self) and self.name.endswith(".tmp") and "00002" in str(self):
            raise OSError(errno.ENOSPC, "No space left on device")  # what a write() raises: no filename
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    proc = run_cli([*fast(tmp_path), "stages=[generate]"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    generate = tmp_path / "cache" / "generate"
    assert len(errors) == 1 and f"no space left on the disk of {generate}/" in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not list(generate.rglob(".tmp-*")) and not list(generate.rglob("*.tmp"))
    assert entries(tmp_path / "cache", "generate") == []
