"""The evaluate stage under metric=paper and metric=strict on the same data, and evaluate.sampling:
every output records its convention, and its numbers follow that convention, recomputed here from the
per-class pixel counts and per-image rows the stage writes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pairedgta.app import run
from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ConfigError
from pairedgta.evaluation.inputs import sampled_conditions
from pairedgta.testing.cli import compose_cfg, fast_overrides

PAPER17 = [c for c in CLASS_NAMES if c not in ("bus", "train")]


def evaluate_dir(summary) -> Path:
    return Path(next(iter(summary["evaluate"].values())))


@pytest.mark.slow
def test_paper_and_strict_outputs_follow_and_record_their_convention(tmp_path):
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer]", "plot.figures=[xi_table]"]
    paper_run = run(compose_cfg(base + ["metric=paper"]))
    strict_run = run(compose_cfg(base + ["metric=strict"]))
    paper, strict = evaluate_dir(paper_run), evaluate_dir(strict_run)
    assert paper != strict  # the convention is part of the evaluate hash

    xi_p, xi_s = pd.read_csv(paper / "xi.csv"), pd.read_csv(strict / "xi.csv")
    assert set(xi_p.convention) == {"paper"} and set(xi_s.convention) == {"strict"}
    # same pixel counts, different conventions on top of them
    np.testing.assert_array_equal(xi_p.reference_pixels, xi_s.reference_pixels)
    absent_seen = supported_seen = False
    for (src, cond), g in xi_p[xi_p.class_id >= 0].groupby(["reference_model", "condition"]):
        ref, ret = g.reference_pixels.to_numpy(float), g.retained_pixels.to_numpy(float)
        clamp = ret / np.maximum(ref, 1)
        np.testing.assert_allclose(g.xi, clamp)
        absent_seen |= bool((ref == 0).any())
        assert list(g[g.in_mean].class_name) == PAPER17
        mean = xi_p[(xi_p.reference_model == src) & (xi_p.condition == cond) & (xi_p.class_id == -1)].xi.item()
        assert mean == pytest.approx(clamp[[CLASS_NAMES.index(c) for c in PAPER17]].mean())
        s = xi_s[(xi_s.reference_model == src) & (xi_s.condition == cond)]
        s_cls = s[s.class_id >= 0]
        assert s_cls.xi.isna().tolist() == (ref == 0).tolist()
        # the support rule: >= metric.min_images images and >= metric.min_pixels pixels to enter the mean
        images = s_cls.images.to_numpy()
        assert ((images > 0) == (ref > 0)).all() and (images <= s_cls.n_pairs).all()
        want = (images >= 3) & (ref >= 1000)
        assert s_cls.supported.tolist() == want.tolist()
        assert list(s_cls[s_cls.in_mean].class_name) == [c for c, ok in zip(CLASS_NAMES, want) if ok]
        mean = s[s.class_id == -1].xi.item()
        assert (np.isnan(mean) and not want.any()) or mean == pytest.approx(s_cls.xi[want].mean())
        # a class seen in one image has no interval: every resample that defines it gives the same ratio
        one = s_cls[images == 1]
        assert one.ci_low.isna().all() and one.ci_high.isna().all()
        supported_seen |= bool(want.any()) and bool((~want & (ref > 0)).any())
    assert absent_seen  # the tiny reference model leaves classes without pseudo-label pixels
    assert supported_seen  # some condition has both supported classes and defined but unsupported ones
    summary = json.loads((strict / "summary.json").read_text())
    assert summary["convention"]["min_images"] == 3 and summary["convention"]["min_pixels"] == 1000
    assert json.loads((paper / "summary.json").read_text())["convention"]["min_images"] == 0
    # the tables show the unsupported cells, marked, and never make them the best of a column
    md = (Path(strict_run["plot"]) / "table1_xi.md").read_text()
    assert "\u2020 too little support" in md and "\u2020" in md.split("\n## ", 1)[1]
    assert "\u2020" not in (Path(paper_run["plot"]) / "table1_xi.md").read_text()

    ag_p, ag_s = pd.read_csv(paper / "pixel_agreement.csv", dtype={"pair_id": str}), pd.read_csv(strict / "pixel_agreement.csv", dtype={"pair_id": str})
    for ag, mode in ((ag_p, "per_image"), (ag_s, "pooled")):
        assert set(ag.convention) == {"paper" if mode == "per_image" else "strict"}
        for cond, g in ag.groupby("condition"):
            per = g[g.pair_id != "ALL"]
            total = g[g.pair_id == "ALL"].iloc[0]
            assert total.aggregation == mode
            want = ((per.agree_reference_pixels / per.valid_pixels).mean() if mode == "per_image"
                    else per.agree_reference_pixels.sum() / per.valid_pixels.sum())
            assert total.agreement_reference == pytest.approx(want)

    for d, headline, name in ((paper, "nonzero", "paper"), (strict, "top_m", "strict")):
        rho = pd.read_csv(d / "rho_valid.csv")
        # the headline selection, over at least metric.rho.min_frames frames (fewer: the value stays, no headline)
        assert (rho.headline == ((rho.selection == headline) & (rho.n_frames >= rho.min_frames))).all()
        assert set(rho.convention) == {name}
        summary = json.loads((d / "summary.json").read_text())
        assert summary["convention"]["name"] == name and summary["convention"]["rho_headline"] == headline
        assert summary["sampling"] == "all"
        for cond, by_class in summary["rho_valid_headline"].items():
            for cls, value in by_class.items():
                row = rho[(rho.condition == cond) & (rho.class_name == cls) & (rho.selection == headline)].rho.item()
                assert (value is None and np.isnan(row)) or value == pytest.approx(row, nan_ok=True)

    # Table 1 from the paper-convention evaluation: the 17 classes of the paper, absent ones as 0
    table = pd.read_csv(Path(paper_run["plot"]) / "table1_xi.csv")
    assert [c for c in table.columns if c in CLASS_NAMES] == PAPER17


@pytest.mark.slow
def test_random_one_sampling_draws_one_adverse_condition_per_group(tmp_path):
    conds = ["Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY"]
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer]", "stages=[generate,pseudolabel,evaluate]",
                                       "generate.num_scenes=5", "evaluate.sampling=random_one", "evaluate.sampling_seed=3"]
    d = evaluate_dir(run(compose_cfg(base)))
    agree = pd.read_csv(d / "pixel_agreement.csv", dtype={"pair_id": str})
    per = agree[agree.pair_id != "ALL"]
    for pair_id, g in per.groupby("pair_id"):
        want = sampled_conditions(pair_id, conds, "Day-EXTRASUNNY", "random_one", 3)
        assert sorted(g.condition) == sorted(want) and len(want) == 2
    summary = json.loads((d / "summary.json").read_text())
    assert summary["sampling"] == "random_one" and summary["sampling_seed"] == 3
    assert summary["n_pairs"]["Day-EXTRASUNNY"] == 5
    assert summary["n_pairs"].get("Day-RAIN", 0) + summary["n_pairs"].get("Night-EXTRASUNNY", 0) == 5
    # groups_per_condition counts the groups that drew each condition, not those that have its image
    assert summary["groups_per_condition"] == {c: summary["n_pairs"].get(c, 0) for c in conds}
    other = evaluate_dir(run(compose_cfg(base[:-1] + ["evaluate.sampling_seed=4"])))
    assert other != d  # the seed is in the evaluate hash
    with pytest.raises(ConfigError, match="evaluate.sampling='one'"):
        run(compose_cfg(base[:-2] + ["evaluate.sampling=one"]))


def test_each_metric_config_names_its_convention():
    from omegaconf import OmegaConf

    from pairedgta.metrics.conventions import CONVENTIONS, convention_from_config
    from pairedgta.testing.cli import CONF

    names = {p.stem: OmegaConf.load(p).convention for p in (CONF / "metric").glob("*.yaml")}
    assert names == {c: c for c in CONVENTIONS}
    with pytest.raises(ConfigError, match="metric.rho.selections: unknown \\['best'\\]"):
        convention_from_config({"convention": "strict", "rho": {"selections": ["best"]}})


def test_sampled_conditions_are_deterministic_and_cover_the_conditions():
    conds = ["Day-EXTRASUNNY", "Day-RAIN", "Day-FOGGY", "Night-EXTRASUNNY"]
    picks = [sampled_conditions(f"{i:05d}", conds, "Day-EXTRASUNNY", "random_one", 0) for i in range(200)]
    assert all(p[0] == "Day-EXTRASUNNY" and len(p) == 2 and p[1] != "Day-EXTRASUNNY" for p in picks)
    counts = pd.Series([p[1] for p in picks]).value_counts()
    # a time of day first (Day or Night, 1/2 each), then a weather of it: Day-RAIN/Day-FOGGY ~ 50 each
    assert set(counts.index) == set(conds[1:]) and 75 < counts["Night-EXTRASUNNY"] < 125
    assert 25 < counts["Day-RAIN"] < 75 and 25 < counts["Day-FOGGY"] < 75
    assert picks == [sampled_conditions(f"{i:05d}", conds, "Day-EXTRASUNNY", "random_one", 0) for i in range(200)]
    assert picks != [sampled_conditions(f"{i:05d}", conds, "Day-EXTRASUNNY", "random_one", 1) for i in range(200)]
    # independent of the order the groups are visited in and of the other groups
    assert sampled_conditions("00007", conds, "Day-EXTRASUNNY", "random_one", 0) == picks[7]
    assert sampled_conditions("x", conds, "Day-EXTRASUNNY", "all", 0) == conds


def test_random_one_draws_a_time_of_day_then_a_weather_as_the_authors_loader():
    """On the paper grid a Day condition for ~1/3 of the groups (the released data: 41 of 101), each of
    the two Day weathers ~1/6, each Sunset and Night condition ~1/9 (not 1/8 each)."""
    times, weathers = ("Day", "Sunset", "Night"), ("EXTRASUNNY", "RAIN", "FOGGY")
    conds = [f"{t}-{w}" for t in times for w in weathers]
    n = 9000
    drawn = pd.Series([sampled_conditions(f"{i:05d}", conds, "Day-EXTRASUNNY", "random_one", 0)[1]
                       for i in range(n)]).value_counts() / n
    assert "Day-EXTRASUNNY" not in drawn
    assert drawn[[c for c in drawn.index if c.startswith("Day")]].sum() == pytest.approx(1 / 3, abs=0.02)
    for c in ("Day-RAIN", "Day-FOGGY"):
        assert drawn[c] == pytest.approx(1 / 6, abs=0.015)
    for c in conds[3:]:
        assert drawn[c] == pytest.approx(1 / 9, abs=0.015)


def test_support_rule_values_are_checked_with_the_key_named():
    from pairedgta.metrics.conventions import convention_from_config

    conv = convention_from_config({"convention": "strict", "min_images": 2, "min_pixels": 10})
    assert conv.supported([1, 2, 5], [100, 9, 10]).tolist() == [False, False, True]
    for key, value in (("min_images", -1), ("min_pixels", 1.5), ("min_images", "many")):
        with pytest.raises(ConfigError, match=f"metric.{key}=.* is invalid; set it to an integer >= 0"):
            convention_from_config({"convention": "strict", key: value})
