"""One model placed against a population (+experiment=model_report): the rank, percentile and correlation code by
hand on small tables, the planning of subject + population, and the whole report through the CLI."""
from __future__ import annotations

import math
import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import percentileofscore, spearmanr

from pairedgta.errors import ConfigError
from pairedgta.metrics.model_report import spearman_masked, standing, standing_interval, standing_rows, tracking

POPULATION = ["tiny_ddrnet", "tiny_pidnet", "tiny_deeplabv3plus"]


# -- rank and percentile ----------------------------------------------------------------------------------------------
def test_rank_and_percentile_by_hand_with_ties():
    # 0.7 beats it, 0.2 is below, two members tie: rank 2 of 5 (the ties share the better rank), (1 + 2/2) / 4 = 50 %
    s = standing(0.5, [0.2, 0.5, 0.7, 0.5])
    assert (s["rank"], s["n"], s["percentile"], s["n_population"]) == (2, 5, 50.0, 4)
    assert s["percentile"] == percentileofscore([0.2, 0.5, 0.7, 0.5], 0.5, kind="mean")
    top = standing(0.9, [0.2, 0.5, 0.7])
    assert (top["rank"], top["percentile"]) == (1, 100.0)
    bottom = standing(0.1, [0.2, 0.5, 0.7])
    assert (bottom["rank"], bottom["n"], bottom["percentile"]) == (4, 4, 0.0)
    # a float that differs in the last bits is a tie, not a win
    assert standing(0.3, [0.1 + 0.2])["percentile"] == 50.0


def test_a_loss_ranks_the_smaller_one_first():
    s = standing(0.10, [0.05, 0.20, 0.30], higher_is_better=False)  # loses more than 0.05, less than the others
    assert (s["rank"], s["percentile"]) == (2, 200 / 3)


def test_a_population_of_one_or_two():
    assert standing(0.3, [0.1]) == {"rank": 1.0, "n": 2.0, "percentile": 100.0, "n_population": 1.0}
    assert standing(0.3, [0.3])["rank"] == 1 and standing(0.3, [0.3])["percentile"] == 50.0
    two = standing(0.2, [0.1, 0.3])
    assert (two["rank"], two["n"], two["percentile"]) == (2, 3, 50.0)


def test_undefined_values_are_left_out_and_said():
    s = standing(0.4, [np.nan, 0.2, 0.6])  # a member without a value in this condition: n says so
    assert (s["rank"], s["n"], s["n_population"], s["percentile"]) == (2, 3, 2, 50.0)
    none = standing(np.nan, [0.2, 0.6])
    assert math.isnan(none["rank"]) and math.isnan(none["percentile"])
    empty = standing(0.4, [np.nan, np.nan])
    assert math.isnan(empty["percentile"]) and empty["n_population"] == 0


def test_the_percentile_interval_is_never_zero_width():
    rng = np.random.default_rng(0)
    pop = rng.uniform(0, 1, size=(200, 5))
    # the subject above every member in every resample: no interval rather than a certain-looking [100, 100]
    lo, hi = standing_interval(np.full(200, 2.0), pop, 0.95)
    assert math.isnan(lo) and math.isnan(hi)
    lo, hi = standing_interval(rng.uniform(0, 1, 200), pop, 0.95)  # it moves among them: an interval
    assert 0 <= lo < hi <= 100
    rows = standing_rows(np.array([0.5, np.nan]), np.array([[0.1, 0.9], [0.1, 0.9]]))
    assert rows["percentile"][0] == 50.0 and math.isnan(rows["percentile"][1])


# -- does xi track ground truth -----------------------------------------------------------------------------------
def test_spearman_by_hand():
    x, y = np.array([1.0, 2.0, 3.0, 4.0]), np.array([1.0, 3.0, 2.0, 4.0])
    assert spearman_masked(x, y)[0] == pytest.approx(1 - 6 * 2 / (4 * 15))  # d = 0, 1, 1, 0
    # ties: average ranks, as scipy
    xt, yt = np.array([1.0, 1.0, 2.0, 3.0]), np.array([2.0, 1.0, 3.0, 3.0])
    assert spearman_masked(xt, yt)[0] == pytest.approx(spearmanr(xt, yt).statistic)
    # a model without a value drops out of its condition; fewer than 3 models, or a constant column: undefined
    assert spearman_masked(np.array([1.0, np.nan, 2.0, 3.0]), np.array([1.0, 5.0, 2.0, 3.0]))[0] == pytest.approx(1.0)
    assert math.isnan(spearman_masked(np.array([1.0, 2.0]), np.array([2.0, 1.0]))[0])
    assert math.isnan(spearman_masked(np.array([1.0, 1.0, 1.0]), np.array([1.0, 2.0, 3.0]))[0])
    # a draw of models with replacement: a model drawn twice counts once towards the 3
    draws = np.array([[0, 0, 1, 1], [0, 1, 2, 2]])
    x4 = np.array([1.0, 2.0, 3.0, 4.0])
    rho = spearman_masked(x4[draws], x4[draws], draws)
    assert math.isnan(rho[0]) and rho[1] == pytest.approx(1.0)


def test_tracking_within_each_condition_with_intervals_over_models_and_scenes():
    rng = np.random.default_rng(1)
    xi = rng.uniform(0.2, 0.8, size=(8, 3))
    gt = xi + rng.normal(0, 0.05, size=(8, 3))
    gt[:, 2] = np.nan  # a condition without ground truth: undefined, out of the mean
    scene_xi = xi[:, None, :] + rng.normal(0, 0.02, size=(8, 100, 3))
    scene_gt = gt[:, None, :] + rng.normal(0, 0.02, size=(8, 100, 3))
    rows = tracking(xi, gt, ["A", "B", "C"], scene_xi, scene_gt, resamples=100, confidence=0.9, seed=0, n_scenes=6)
    by = {r["condition"]: r for r in rows}
    for c, i in (("A", 0), ("B", 1)):
        assert by[c]["spearman"] == pytest.approx(spearmanr(xi[:, i], gt[:, i]).statistic)
        assert by[c]["n_models"] == 8
        for kind in ("scene", "model"):
            lo, hi = by[c][f"{kind}_ci_low"], by[c][f"{kind}_ci_high"]
            assert lo < hi and lo <= by[c]["spearman"] + 1e-9, (c, kind, lo, hi)
    assert math.isnan(by["C"]["spearman"]) and by["C"]["n_models"] == 0
    assert math.isnan(by["C"]["model_ci_low"]) and math.isnan(by["C"]["scene_ci_low"])
    assert by["mean"]["spearman"] == pytest.approx((by["A"]["spearman"] + by["B"]["spearman"]) / 2)
    assert by["mean"]["n_conditions"] == 2 and by["mean"]["n_scenes"] == 6


def test_tracking_never_shows_a_zero_width_interval():
    # every model draw of a perfectly monotone column gives +1: no interval, not [1, 1]
    xi = np.array([[0.1], [0.2], [0.3], [0.4]])
    rows = tracking(xi, xi * 2, ["A"], resamples=200, seed=0)
    assert rows[0]["spearman"] == pytest.approx(1.0)
    assert math.isnan(rows[0]["model_ci_low"]) and math.isnan(rows[0]["model_ci_high"])
    assert math.isnan(rows[0]["scene_ci_low"])  # no scene resamples given
    # a population of one (two ranked models): no correlation and no interval
    two = tracking(np.array([[0.1], [0.2]]), np.array([[0.3], [0.1]]), ["A"], resamples=200)
    assert math.isnan(two[0]["spearman"]) and math.isnan(two[0]["model_ci_low"]) and math.isnan(two[-1]["spearman"])


# -- planning: the subject and its population ------------------------------------------------------------------------
def _run(overrides: list[str]):
    from pairedgta import schema
    from omegaconf import OmegaConf

    from pairedgta.testing.cli import compose_cfg

    return schema.parse(OmegaConf.to_container(compose_cfg(["+experiment=model_report", *overrides]), resolve=True))


def test_the_run_evaluates_the_model_and_its_population_the_model_first():
    from pairedgta.figures.report_population import zoo
    from pairedgta.stages.planning import run_models

    models = run_models(_run(["model=demo_ddrnet"]), model_chosen=True)
    names = [m["name"] for m in models.evaluated]
    # the zoo by default, without the model itself and without the reference model (never ranked)
    assert names[0] == "demo_ddrnet" and set(names[1:]) == set(zoo()) - {"demo_ddrnet", "demo_segformer"}
    assert models.reference["name"] == "demo_segformer" and len(names) == len(set(names))
    listed = "report.population=[demo_pidnet,tiny_mask2former,demo_segformer]"
    given = run_models(_run(["model=tiny_mask2former", listed]), model_chosen=True)
    assert [m["name"] for m in given.evaluated] == ["tiny_mask2former", "demo_pidnet"]


def test_a_bad_population_is_one_line():
    from pairedgta.config_checks import check_run_config
    from pairedgta.stages.planning import run_models
    from omegaconf import OmegaConf

    from pairedgta.testing.cli import compose_cfg

    cfg = OmegaConf.to_container(compose_cfg(["+experiment=model_report", "model=demo_ddrnet",
                                              "report.population=[demo_pidnet,demo_pidnett]"]), resolve=True)
    with pytest.raises(ConfigError, match=r"^report.population\[1\]: unknown model 'demo_pidnett'; choose one of: "):
        check_run_config(cfg)
    with pytest.raises(ConfigError, match="use a list of model names without repeats"):
        _run(["report.population=[demo_pidnet,demo_pidnet]"])
    with pytest.raises(ConfigError, match="^model_report: the model to report is demo_segformer, the reference model"):
        run_models(_run([]))
    with pytest.raises(ConfigError, match=r"no model to place demo_pidnet against besides itself and the reference"):
        run_models(_run(["model=demo_pidnet", "report.population=[demo_pidnet,demo_segformer]"]), model_chosen=True)


def test_the_plot_key_names_the_subject_and_its_population():
    from types import SimpleNamespace

    from pairedgta.figures.report_population import cache_key

    def key(*overrides: str) -> dict:
        return cache_key([SimpleNamespace(pseudo=None)], SimpleNamespace(run=_run(list(overrides))))[0]

    a = key("model=demo_ddrnet", "report.population=[demo_pidnet,demo_deeplabv3plus]")
    b = key("model=demo_pidnet", "report.population=[demo_ddrnet,demo_deeplabv3plus]")
    assert a["subject"] == "demo_ddrnet" and a["population"] == ["demo_pidnet", "demo_deeplabv3plus"]
    assert a != b  # the same three evaluations, another report


# -- through the CLI ------------------------------------------------------------------------------------------------
NETS = '''
import torch


def _net(seed, width):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Conv2d(3, width, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(width, 19, 1))


def mine_a():
    return _net(0, 8)


def mine_b():
    return _net(1, 6)
'''


def _table(md: str, heading: str) -> pd.DataFrame:
    part = md.split(f"## {heading}", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in part.splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    return pd.DataFrame([[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]], columns=header)


def _evaluations(out: str) -> dict[str, Path]:
    return {m.group(1): Path(m.group(2)) for m in re.finditer(r"^  evaluate \[(\S+)\]: (\S+)$", out, re.M)}


@pytest.mark.slow
def test_a_model_placed_against_a_population_through_the_cli(tmp_path, monkeypatch):
    from pairedgta.testing.cli import fast_overrides, run_cli

    module = f"report_nets_{abs(hash(tmp_path.name)) % 10**8}"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent(NETS))
    monkeypatch.syspath_prepend(str(tmp_path))
    base = [o for o in fast_overrides(tmp_path) if not o.startswith("model=")] + [
        "+experiment=model_report", f"report.population=[{','.join(POPULATION)}]", "plot.formats=[png,pdf]",
        "report.worst_cases=2", "model=python"]

    proc = run_cli([*base, f"model.target={module}:mine_a"], tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    page = Path(re.search(r"model report of mine_a \(model_report.md beside it\): (\S+)", out).group(1))
    for suffix in (".png", ".pdf", ".md"):
        assert page.with_suffix(suffix).is_file(), suffix
    md = page.with_suffix(".md").read_text()
    assert md.startswith("# Model report: mine_a") and "tiny_segformer's pseudo-labels" in md

    # the ranks and percentiles, recomputed from the evaluate stage's own tables
    evaluated = _evaluations(proc.stdout)
    assert list(evaluated) == ["mine_a", *POPULATION]  # the model first; the reference is not evaluated
    xi, gt = {}, {}
    for name, path in evaluated.items():
        t = pd.read_csv(path / "xi.csv")
        xi[name] = t[(t.reference_model != "ground_truth") & (t.class_name == "mean")].set_index("condition")["xi"]
        g = pd.read_csv(path / "gt_iou.csv")
        gt[name] = g[g.class_name == "mean"].set_index("condition")["iou"]
    table = _table(md, "Per adverse condition")
    assert list(table["condition"]) == ["Day-RAIN", "Night-EXTRASUNNY"]
    for row in table.to_dict("records"):
        for values, rank_col, pct_col in ((xi, "ξ rank", "ξ percentile"), (gt, "GT mIoU rank", "GT mIoU percentile")):
            s = values["mine_a"][row["condition"]]
            pop = [values[m][row["condition"]] for m in POPULATION]
            rank = 1 + sum(p > s + 1e-12 for p in pop)  # tied members share the better rank
            assert row[rank_col] == f"{rank}/4", (row, rank_col)
            assert row[pct_col] == f"{percentileofscore(pop, s, kind='mean'):.1f}", (row, pct_col)
    tracked = _table(md, "How well ξ tracks ground truth on these scenes")
    assert tracked["n models"].tolist()[:2] == ["4", "4"] and tracked["condition"].iloc[-1].startswith("mean over")
    assert len(_table(md, "Where it loses most")) == 2 and len(_table(md, "Worst images")) == 2

    # a sweep over the researcher's models (-m): one report per job, the population's evaluations the cache's
    again = run_cli([*base, f"model.target={module}:mine_a,{module}:mine_b"], tmp_path, multirun=True)
    out2 = again.stdout + again.stderr
    assert again.returncode == 0, out2[-3000:]
    for name in POPULATION:
        assert out2.count(f"evaluate [{name}]: cache hit") == 2, name  # in each job
        assert _evaluations(again.stdout)[name] == evaluated[name]
    assert "evaluate [mine_a]: cache hit" in out2 and "evaluate [mine_b]: computing" in out2
    assert "model report of mine_a" in out2
    page2 = Path(re.search(r"model report of mine_b \(model_report.md beside it\): (\S+)", out2).group(1))
    assert page2.parent != page.parent and page2.with_suffix(".md").read_text().startswith("# Model report: mine_b")
    sys.modules.pop(module, None)
