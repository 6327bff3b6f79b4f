"""The stage graph and its cache, run in-process on the composed config tree."""
from __future__ import annotations

import json
import shutil

import pytest

from pairedgta.app import run
from pairedgta.errors import PairedGTAError
from pairedgta.stages import generate as generate_stage
from pairedgta.testing.cli import compose_cfg, fast_overrides


def hits(summary):
    return {(s["stage"], s["label"]): s["hit"] for s in summary["stages"]}


@pytest.mark.slow
def test_cache_hit_selective_recompute_and_force(tmp_path):
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer]", "plot.figures=[xi_models]"]  # one figure: the plot's time
    first = run(compose_cfg(base))
    assert not any(hits(first).values())
    again = run(compose_cfg(base))
    assert all(hits(again).values()), again["stages"]

    changed_metric = run(compose_cfg(base + ["metric.rho.m=5"]))
    h = hits(changed_metric)
    assert h[("generate", "")] and h[("pseudolabel", "[tiny_segformer]")]
    assert not h[("evaluate", "[tiny_segformer]")] and not h[("plot", "")]

    changed_model = run(compose_cfg(base[:-1] + ["models=[tiny_mask2former]"]))
    h = hits(changed_model)
    assert h[("pseudolabel", "[tiny_segformer]")] and not h[("evaluate", "[tiny_mask2former]")]

    # runtime-only keys do not change hashes
    assert all(hits(run(compose_cfg(base + ["evaluate.batch_size=1", "pseudolabel.batch_size=1"]))).values())

    forced = run(compose_cfg(base + ["force=[evaluate]"]))
    h = hits(forced)
    assert not h[("evaluate", "[tiny_segformer]")] and h[("pseudolabel", "[tiny_segformer]")]
    assert h[("plot", "")]  # same evaluate hash -> the plot input is unchanged


@pytest.mark.slow
def test_killed_run_leftovers_are_never_a_hit(tmp_path):
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer]", "stages=[generate,pseudolabel]"]
    summary = run(compose_cfg(base))
    pseudo = next(s for s in summary["stages"] if s["stage"] == "pseudolabel")
    final = tmp_path / "cache" / "pseudolabel" / pseudo["key"]
    # simulate a run killed while writing: a temp dir with partial content, no final dir
    shutil.rmtree(final)
    partial = final.with_name(f".tmp-{pseudo['key']}-4242-deadbeef")
    (partial / "labels").mkdir(parents=True)
    (partial / "labels" / "00000.png").write_bytes(b"partial")
    again = run(compose_cfg(base))
    assert not hits(again)[("pseudolabel", "[tiny_segformer]")]
    assert (final / "manifest.json").is_file() and len(list((final / "labels").glob("*.png"))) == 3


@pytest.mark.slow
def test_missing_input_names_the_stage_to_run(tmp_path):
    with pytest.raises(PairedGTAError, match=r"generate: no cached output.*stages=\[generate"):
        run(compose_cfg(fast_overrides(tmp_path) + ["stages=[evaluate,plot]", "models=[tiny_segformer]"]))
    run(compose_cfg(fast_overrides(tmp_path) + ["stages=[generate]"]))
    with pytest.raises(PairedGTAError, match=r"pseudolabel.*run it first, e.g. stages=\[pseudolabel"):
        run(compose_cfg(fast_overrides(tmp_path) + ["stages=[evaluate,plot]", "models=[tiny_segformer]"]))
    # and nothing half-written was left behind
    assert not list((tmp_path / "cache").glob("*/.tmp-*"))


@pytest.mark.slow
def test_hash_ignores_run_dir_and_time(tmp_path):
    a = run(compose_cfg(fast_overrides(tmp_path) + ["stages=[generate]"]))
    b = run(compose_cfg(fast_overrides(tmp_path) + ["stages=[generate]", "hydra.run.dir=/elsewhere"]))
    assert a["stages"][0]["key"] == b["stages"][0]["key"] and b["stages"][0]["hit"]


@pytest.mark.slow
def test_generate_resumes_after_a_crash(tmp_path, monkeypatch):
    overrides = fast_overrides(tmp_path) + ["stages=[generate]"]
    real = generate_stage.render_scene
    calls = []

    def crash_on_third(k, *args, **kw):
        calls.append(k)
        if k == 2:
            raise KeyboardInterrupt
        return real(k, *args, **kw)

    monkeypatch.setattr(generate_stage, "render_scene", crash_on_third)
    with pytest.raises(KeyboardInterrupt):
        run(compose_cfg(overrides))
    assert not [p for p in (tmp_path / "cache" / "generate").iterdir() if not p.name.startswith(".")]
    partial = next((tmp_path / "cache" / "generate").glob(".partial-*"))
    done = sorted(p.name for p in (partial / "scenes").iterdir())
    assert done == ["00000", "00001"]
    stamp = (partial / "scenes" / "00000" / "timings.json").stat().st_mtime_ns
    calls.clear()
    monkeypatch.setattr(generate_stage, "render_scene", real)
    summary = run(compose_cfg(overrides))
    out = tmp_path / "cache" / "generate" / summary["stages"][0]["key"]
    assert (out / "scenes" / "00000" / "timings.json").stat().st_mtime_ns == stamp
    index = json.loads((out / "index.json").read_text())
    assert [s["scene_id"] for s in index["scenes"]] == ["00000", "00001", "00002"]


@pytest.mark.slow
def test_generate_is_deterministic_and_paired(tmp_path):
    import numpy as np
    from PIL import Image

    s1 = run(compose_cfg(fast_overrides(tmp_path / "a") + ["stages=[generate]"]))
    s2 = run(compose_cfg(fast_overrides(tmp_path / "b") + ["stages=[generate]"]))
    d1 = tmp_path / "a" / "cache" / "generate" / s1["stages"][0]["key"] / "scenes" / "00001"
    d2 = tmp_path / "b" / "cache" / "generate" / s2["stages"][0]["key"] / "scenes" / "00001"
    assert (d1 / "descriptor.json").read_text() == (d2 / "descriptor.json").read_text()
    for c in ("Day-EXTRASUNNY", "Night-EXTRASUNNY"):
        assert np.array_equal(np.asarray(Image.open(d1 / f"{c}.png")), np.asarray(Image.open(d2 / f"{c}.png")))
    labels = [np.asarray(Image.open(d1 / f"{c}_labels.png")) for c in ("Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY")]
    assert all(np.array_equal(labels[0], lab) for lab in labels[1:])
    day, night = (np.asarray(Image.open(d1 / f"{c}.png")).astype(float) for c in ("Day-EXTRASUNNY", "Night-EXTRASUNNY"))
    assert night.mean() < 0.6 * day.mean()


def test_two_jobs_on_one_hash_first_rename_wins(tmp_path):
    from pairedgta.cache import StageCache

    cache = StageCache(tmp_path)
    with cache.build("evaluate", "abc", {"job": "slow"}) as slow:
        (slow / "xi.csv").write_text("slow")
        with cache.build("evaluate", "abc", {"job": "fast"}) as fast:
            (fast / "xi.csv").write_text("fast")
        assert cache.is_hit("evaluate", "abc")
    assert (tmp_path / "evaluate" / "abc" / "xi.csv").read_text() == "fast"
    assert cache.manifest("evaluate", "abc")["job"] == "fast"
    assert [p.name for p in (tmp_path / "evaluate").iterdir()] == ["abc"]


@pytest.mark.slow
def test_replacing_local_weights_behind_the_same_path_is_not_a_hit(tmp_path):
    from pairedgta.models import build_model

    weights = tmp_path / "weights"
    build_model("tiny_segformer").module.save_pretrained(weights)
    base = fast_overrides(tmp_path) + ["models=null", "model=segformer_b0", f"model.path={weights}",
                                       "stages=[generate,pseudolabel,evaluate]"]
    first = hits(run(compose_cfg(base)))
    assert not first[("evaluate", "[segformer_b0]")]
    assert hits(run(compose_cfg(base)))[("evaluate", "[segformer_b0]")]
    build_model("tiny_segformer", init_seed=1).module.save_pretrained(weights)  # same path, new weights
    again = hits(run(compose_cfg(base)))
    assert not again[("evaluate", "[segformer_b0]")] and again[("pseudolabel", "[tiny_segformer]")]
