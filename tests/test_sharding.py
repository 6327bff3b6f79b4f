"""Sharded generation (`generate.num_shards`/`generate.shard`) writes the same dataset as one unsharded
run, into the same cache entry, from the CLI as a cluster job would run it."""
from __future__ import annotations

import pytest

import json
from pathlib import Path

from pairedgta.testing.cli import base_overrides, run_cli

pytestmark = pytest.mark.slow  # end to end: the CLI or the stage graph on every test

SMALL = ["+experiment=smoke", "generate.num_scenes=5", "renderer.width=64", "renderer.height=32",
         "conditions.only=[Day-EXTRASUNNY,Day-RAIN,Night-EXTRASUNNY]", "tracking.enabled=false"]


def entries(cache: Path) -> dict[str, Path]:
    return {p.name: p for p in (cache / "generate").glob("[!.]*") if (p / "manifest.json").is_file()}


def files(entry: Path) -> dict[str, bytes]:
    return {p.relative_to(entry).as_posix(): p.read_bytes() for p in sorted((entry / "scenes").rglob("*.png"))}


def test_shards_build_the_unsharded_dataset(tmp_path):
    one, many = tmp_path / "one", tmp_path / "many"
    one.mkdir(), many.mkdir()
    proc = run_cli(SMALL + base_overrides(one) + ["stages=[generate]"], one)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for shard in range(3):
        proc = run_cli(SMALL + base_overrides(many) + ["stages=[generate]", "generate.num_shards=3", f"generate.shard={shard}"], many)
        assert proc.returncode == 0, proc.stderr[-2000:]
        done = entries(many / "cache")
        assert bool(done) is (shard == 2), "the entry is complete only once every shard ran"
    # the unsharded run renders nothing more and goes on with the later stages
    proc = run_cli(SMALL + base_overrides(many) + ["stages=[generate,pseudolabel]"], many)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "generate: cache hit" in proc.stdout + proc.stderr
    (key_one, e_one), = entries(one / "cache").items()
    (key_many, e_many), = entries(many / "cache").items()
    assert key_one == key_many  # shard keys are not part of the dataset's hash
    a, b = files(e_one), files(e_many)
    assert len(a) == 5 * 3 * 4 and a == b  # images, label, instance and transmittance maps byte-identical
    assert json.loads((e_one / "index.json").read_text()) == json.loads((e_many / "index.json").read_text())


def test_bad_shard_keys_are_one_line(tmp_path):
    for extra, message in ((["generate.num_shards=3", "generate.shard=3"], "generate.shard=3 is outside 0..2"),
                           (["generate.num_shards=0"], "generate.num_shards=0"),
                           (["generate.num_shards=2", "generate.shard=1", "force=[generate]"], "would discard other shards")):
        proc = run_cli(SMALL + base_overrides(tmp_path) + ["stages=[generate]", *extra], tmp_path)
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert message in proc.stderr and "Traceback" not in proc.stderr


def test_a_shard_job_with_later_stages_says_what_to_do(tmp_path):
    proc = run_cli(SMALL + base_overrides(tmp_path) + ["generate.num_shards=2", "generate.shard=0"], tmp_path)
    assert proc.returncode == 2
    assert "run the remaining shards" in proc.stderr


EVAL_FILES = ("xi.csv", "rho_valid.csv", "pixel_agreement.csv", "frame_counts.csv", "gt_iou.csv", "summary.json")


def evaluations(cache: Path) -> dict[str, Path]:
    return {json.loads((p / "manifest.json").read_text())["config"]["model"]["name"]: p
            for p in (cache / "evaluate").glob("[!.]*") if (p / "manifest.json").is_file()}


def test_sharded_evaluation_merges_to_the_unsharded_result(tmp_path):
    one, many = tmp_path / "one", tmp_path / "many"
    one.mkdir(), many.mkdir()
    data = SMALL + ["stages=[generate,pseudolabel,evaluate]", "metric.bootstrap.resamples=30"]
    proc = run_cli(data + base_overrides(one) + ["evaluate.num_workers=0"], one)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for shard in range(2):
        proc = run_cli(data + base_overrides(many) + ["evaluate.num_shards=3", f"evaluate.shard={shard}",
                                                       "evaluate.num_workers=2"], many)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert not evaluations(many / "cache"), "no entry while a shard is missing"
    parts = list((many / "cache" / "evaluate").glob(".parts-*/part-*.json"))
    assert len(parts) == 2 * 2  # two shards x two models
    # the unsharded run merges the two shards' partial sums and computes the third shard's groups itself
    proc = run_cli(data + base_overrides(many), many)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "merging" in proc.stdout + proc.stderr
    a, b = evaluations(one / "cache"), evaluations(many / "cache")
    assert set(a) == set(b) == {"tiny_segformer", "tiny_mask2former"}
    for model in a:
        assert a[model].name == b[model].name  # same hash: shard keys and workers are not in it
        for name in EVAL_FILES:
            assert (a[model] / name).read_bytes() == (b[model] / name).read_bytes(), (model, name)
    assert not list((many / "cache" / "evaluate").glob(".parts-*")), "merged partial sums are removed"


def test_a_complete_set_of_shards_finalises_the_entry(tmp_path):
    data = SMALL + base_overrides(tmp_path) + ["stages=[generate,pseudolabel,evaluate]", "metric.bootstrap.resamples=10",
                                              "models=[tiny_segformer]"]
    for shard in range(2):
        proc = run_cli(data + ["evaluate.num_shards=2", f"evaluate.shard={shard}"], tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert set(evaluations(tmp_path / "cache")) == {"tiny_segformer"}


def test_sharded_evaluation_under_the_paper_convention_and_random_one_sampling(tmp_path):
    """The authors' settings (absent class = 0, per-image agreement, one random adverse condition per
    group) merge from shards to the unsharded bytes too: the draw depends on the group, not the shard."""
    one, many = tmp_path / "one", tmp_path / "many"
    one.mkdir(), many.mkdir()
    data = SMALL + ["stages=[generate,pseudolabel,evaluate]", "metric.bootstrap.resamples=20", "models=[tiny_segformer]",
                    "metric=paper", "evaluate.sampling=random_one", "evaluate.sampling_seed=5"]
    proc = run_cli(data + base_overrides(one), one)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = run_cli(data + base_overrides(many) + ["evaluate.num_shards=2", "evaluate.shard=1"], many)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = run_cli(data + base_overrides(many), many)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "merging" in proc.stdout + proc.stderr
    (a,), (b,) = evaluations(one / "cache").values(), evaluations(many / "cache").values()
    assert a.name == b.name
    for name in EVAL_FILES:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    summary = json.loads((a / "summary.json").read_text())
    assert summary["convention"]["name"] == "paper" and summary["sampling"] == "random_one"
    adverse = {c: n for c, n in summary["groups_per_condition"].items() if c != "Day-EXTRASUNNY"}
    assert sum(adverse.values()) == 5  # one adverse condition per group
    assert summary["groups_per_condition"] == {c: summary["n_pairs"].get(c, 0) for c in summary["groups_per_condition"]}
