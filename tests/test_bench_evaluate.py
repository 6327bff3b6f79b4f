"""experiments/bench_evaluate.py's arithmetic (issue 48, item 5): its columns once read "forward share 0.0 %" and
"decode+count 100.0 %" because the timed method was no longer the one evaluate called, and its ratio compared
four evaluated models with one bare forward. These tests check what it prints adds up, without timing anything."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def bench():
    spec = importlib.util.spec_from_file_location("bench_evaluate", ROOT / "experiments" / "bench_evaluate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_columns_add_up_and_the_ratio_is_as_stated():
    b = bench()
    c = b.columns({"images": 48, "count": 4.0, "forward": 3.0, "write": 1.0, "bare": 3.0})
    assert c["eval_ips"] == 12.0 and c["bare_ips"] == 16.0 and c["ratio"] == 0.75
    assert (c["forward_share"], c["other_share"], c["write_share"]) == (0.6, 0.2, 0.2)
    # a forward timed longer than its stage (clock jitter) is capped: no negative "other" column
    c = b.columns({"images": 10, "count": 1.0, "forward": 1.2, "write": 0.0, "bare": 1.0, "steady": 0.5})
    assert c["other_share"] == 0.0 and c["forward_share"] == 1.0
    assert c["stage_steady_ips"] == 20.0 and c["steady_ratio"] == 2.0  # from the first decoded group on
    assert "100.0%" in b.row(0, c) and "-" not in b.row(0, c).split()[6]
    # against the forward with the estimators' maps, where it was measured
    c = b.columns({"images": 48, "count": 4.0, "forward": 3.0, "write": 1.0, "bare": 3.0, "maps": 3.6})
    assert c["maps_ips"] == pytest.approx(48 / 3.6) and c["maps_ratio"] == pytest.approx(0.9)
    assert b.row(0, c).split()[-2:] == ["13.33", "0.90"]


def test_the_evaluated_model_is_the_benchmarked_one_alone():
    """models=null: the main job's list of four models no longer rides along into the stage's time."""
    args = bench().overrides(Path("/d"), Path("/c"), "tiny_segformer", 0, 4, "-", "cpu")
    assert "models=null" in args and "model=tiny_segformer" in args and "reference_model=tiny_segformer" in args


def test_a_full_paper_graph_is_built_with_its_own_widths():
    """`--full` once built SegFormer-B5 as B0: a family's default config is its smallest member."""
    args = bench().overrides(Path("/d"), Path("/c"), "segformer_b5", 0, 4, "-", "cpu", full=True)
    arch = [a for a in args if a.startswith("++model.arch=")]
    assert "++model.random_init=true" in args and len(arch) == 1
    assert "hidden_sizes:[64,128,320,512]" in arch[0] and "depths:[3,6,40,3]" in arch[0]
    # a graph whose family has one architecture gets none; an explicit --arch wins
    assert not [a for a in bench().overrides(Path("/d"), Path("/c"), "ddrnet_23", 0, 4, "-", "cpu", full=True)
                if a.startswith("++model.arch=")]
    own = bench().overrides(Path("/d"), Path("/c"), "segformer_b5", 0, 4, "{depths:[1,1,1,1]}", "cpu", full=True)
    assert [a for a in own if a.startswith("++model.arch=")] == ["++model.arch={depths:[1,1,1,1]}"]


class _Fake:
    """A segmenter with a 1x1 convolution for a network: every stage path runs, in milliseconds."""

    @staticmethod
    def build(cfg, device=None, **_):
        import torch

        from pairedgta.models.base import Segmenter
        from pairedgta.models.runtime import RuntimeOptions

        class Fake(Segmenter):
            def _logits(self, images):
                return self.module(images)

        torch.manual_seed(0)
        return Fake("fake", torch.nn.Conv2d(3, 19, 1), RuntimeOptions(device=str(device or "cpu"), batch_size=4))


@pytest.mark.slow
def test_a_measurement_on_a_fake_segmenter_adds_up(tmp_path, monkeypatch):
    import pairedgta.models as models
    import pairedgta.evaluation.work as ev
    import pairedgta.evaluation.pseudolabel as pl

    b = bench()
    for module, name in ((models, "build_model"), (ev, "shared_model"), (pl, "shared_model")):
        monkeypatch.setattr(module, name, _Fake.build)  # the bare forward's model, and the stages'
    b.make_release_dataset(tmp_path / "ds", 3, 64, 32)
    r = b.measure(tmp_path / "ds", tmp_path / "cache", "tiny_ddrnet", 0, 2, "-", repeats=3)
    assert r["images"] == 9 and r["groups"] == 3 and (r["width"], r["height"]) == (64, 32)
    # three stage runs, each between two bare forwards: the reported columns are the median run's
    assert len(r["ratios"]) == 3 and r["ratio"] == pytest.approx(sorted(r["ratios"])[1])
    assert r["ratio_spread"] == pytest.approx(max(r["ratios"]) - min(r["ratios"]))
    assert 0 < r["forward"] <= r["count"] and r["write"] > 0 and r["bare"] > 0 and r["maps"] > 0
    assert r["maps_ratio"] == pytest.approx(r["eval_ips"] / r["maps_ips"])
    assert r["forward_share"] + r["other_share"] + r["write_share"] == pytest.approx(1.0, abs=1e-12)
    assert r["eval_ips"] == pytest.approx(9 / r["count"]) and r["ratio"] == pytest.approx(r["eval_ips"] / r["bare_ips"])
    assert 0 < r["steady"] <= r["count"] and r["steady_ratio"] >= r["ratio"]
    assert list((tmp_path / "cache" / "evaluate").iterdir())  # the stage did run (not a cache hit of nothing)
