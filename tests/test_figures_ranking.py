"""Ranking figure: a class without rho_valid is explained in words, not drawn as a black heatmap."""
from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from pairedgta.figures import ranking  # noqa: E402


def _inputs():
    counts, rho = [], []
    for pair in range(6):
        counts.append({"model": "m", "class_name": "car", "condition": "Night-EXTRASUNNY", "pair_id": pair,
                       "clean_count": 100 * (pair + 1), "adv_count": 80 * (6 - pair)})
        counts.append({"model": "m", "class_name": "person", "condition": "Night-EXTRASUNNY", "pair_id": pair,
                       "clean_count": 30 if pair == 2 else 0, "adv_count": 0})
    for cls, value in (("car", -1.0), ("person", math.nan)):
        for sel in ("top_m", "nonzero"):
            rho.append({"model": "m", "class_name": cls, "condition": "Night-EXTRASUNNY", "selection": sel,
                        "rho": value, "n_frames": 6})
    return [ranking.RankingInput("d", "Night-EXTRASUNNY", pd.DataFrame(counts), pd.DataFrame(rho))]


def test_a_class_without_rho_valid_gets_words_instead_of_a_heatmap(monkeypatch, tmp_path):
    figs = []
    monkeypatch.setattr(ranking, "save", lambda fig, out, stem, formats, dpi: figs.append(fig) or [out / "x.png"])
    paths = ranking.ranking_figure(_inputs(), ["car", "person"], 3, tmp_path, ["png"], 50)
    assert paths and len(figs) == 1
    axes = figs[0].axes
    titles = [a.get_title() for a in axes]
    car = next(a for a in axes if "car" in a.get_title())
    person = next(a for a in axes if "person" in a.get_title())
    assert "top-M -1.000" in car.get_title() and car.collections  # a drawn heatmap
    assert "n/a" in person.get_title() and not person.collections and not person.images
    words = " ".join(t.get_text() for t in person.texts)
    assert "too few frames" in words and "1 of 6 clean" in words and "0 of 6 adverse" in words, titles


def test_one_headline_condition_for_the_ranking_figure_and_the_logged_rho(tmp_path):
    """plot.ranking.condition picks the condition the ranking figure shows and the one whose rho_valid is
    logged without a condition in its name (the run's headline); absent from a dataset, Night-EXTRASUNNY,
    else the first adverse condition."""
    import json

    from pairedgta.conditions import HEADLINE, headline_condition
    from pairedgta.evaluation.work import EvaluateResult

    conds, ref = ["Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY"], "Day-EXTRASUNNY"
    rain = "Day-RAIN"  # plot.ranking.condition
    assert headline_condition(conds, None, ref) == HEADLINE == "Night-EXTRASUNNY"
    assert headline_condition(conds, rain, ref) == "Day-RAIN"
    assert headline_condition(["ACDC-reference", "ACDC-night"], rain, "ACDC-reference") == "ACDC-night"
    assert headline_condition([ref], rain, ref) is None

    rows = [{"model": "m", "class_name": "car", "condition": c, "selection": "top_m", "rho": v}
            for c, v in (("Day-RAIN", 0.2), ("Night-EXTRASUNNY", 0.7))]
    pd.DataFrame(rows).to_csv(tmp_path / "rho_valid.csv", index=False)
    pd.DataFrame(columns=["model", "reference_model", "condition", "class_name", "xi"]).to_csv(tmp_path / "xi.csv")
    (tmp_path / "summary.json").write_text(json.dumps({}))
    e = EvaluateResult("evaluate", "k", tmp_path, True)
    assert e.metrics()["rho_valid/top_m/car"] == 0.7
    assert e.metrics(headline=rain)["rho_valid/top_m/car"] == 0.2


# -- rho_valid from the authors' per-frame counts (plot.frame_counts_csv) ---------------------------------
def _authors_counts(path):
    """Two datasets x one model x two classes in the authors' format. our_dataset/car: clean counts 0..29
    (29 non-zero frames) and adverse = clean plus a wobble, so rho is known from scipy."""
    import numpy as np

    rows = []
    rng = np.random.default_rng(0)
    for dataset, adv_path in (("our_dataset", "/x/Dataset/Night/{p}_Night_EXTRASUNNY.png"),
                              ("acdc", "/x/rgb_anon/night/train/GOPR0351/{p}_rgb_anon.png")):
        for cls in ("person", "car"):
            for p in range(30):
                clean = p * 100 if cls == "car" else int(rng.integers(0, 3)) * 50
                adv = max(0, clean + int(rng.integers(-300, 300)))
                rows.append({"dataset_name": dataset, "model": "SegFormer-B5", "target_class": cls, "pair_id": f"{p:05d}",
                             "clean_count": clean, "adv_count": adv, "clean_path": f"/x/{p}_Day_EXTRASUNNY.png",
                             "adv_path": adv_path.format(p=p)})
    pd.DataFrame(rows).to_csv(path, index=False)
    return path, pd.DataFrame(rows)


@pytest.mark.slow
def test_rho_valid_from_the_authors_frame_counts_through_the_cli(tmp_path):
    import json
    import re
    from pathlib import Path

    import pytest
    from scipy.stats import spearmanr

    from pairedgta.figures import FigureSpec, figure
    from pairedgta.testing.cli import run_cli

    assert figure("authors_ranking") == FigureSpec("authors_ranking", "pairedgta.figures.authors_ranking:draw",
                                                   source="plot.frame_counts_csv",
                                                   key="pairedgta.figures.authors_ranking:cache_key")
    csv, df = _authors_counts(tmp_path / "framewise_target_class_counts.csv")
    cache = tmp_path / "cache"
    args = ["+experiment=night_vs_acdc", "stages=[plot]", f"plot.frame_counts_csv={csv}", f"cache_dir={cache}",
            "tracking.enabled=false", "plot.formats=[png]", "metric.bootstrap.resamples=200"]
    proc = run_cli(args, tmp_path)  # no acdc.root: a run from a given file reads no dataset
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert {p.name for p in cache.iterdir() if not p.name.startswith(".")} == {"plot"}
    out = Path(re.search(r"results: (\S+)", proc.stdout).group(1))
    rho = pd.read_csv(out / "rho_valid.csv")
    assert set(rho.dataset_label) == {"our_dataset", "acdc"}
    assert set(rho.condition) == {"Night-EXTRASUNNY", "ACDC-night"}
    for (dataset, cls), g in df.groupby(["dataset_name", "target_class"]):
        nz = g[g.clean_count > 0]
        want = spearmanr(nz.clean_count, nz.adv_count).statistic
        row = rho[(rho.dataset_label == dataset) & (rho.class_name == cls) & (rho.selection == "nonzero")].iloc[0]
        assert row.rho == pytest.approx(want) and row.n_frames == len(nz)
        assert row.headline and row.convention == "paper"  # night_vs_acdc: the authors' convention
        assert row.ci_low <= row.rho <= row.ci_high
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["rho_valid/our_dataset/SegFormer-B5/nonzero/car"] == pytest.approx(
        rho[(rho.dataset_label == "our_dataset") & (rho.class_name == "car") & (rho.selection == "nonzero")].rho.item())
    from PIL import Image

    assert Image.open(out / "ranking.png").size[0] >= 1200  # readable at the default dpi

    # bad input: one line naming the file or key, before anything is drawn
    bad = df.copy()
    bad.loc[3, "adv_count"] = -4
    bad.to_csv(tmp_path / "neg.csv", index=False)
    df.drop(columns="adv_count").to_csv(tmp_path / "nocol.csv", index=False)
    pd.concat([df, df.head(1)]).to_csv(tmp_path / "dup.csv", index=False)
    for name, message in (("neg.csv", "adv_count -4 in row 5 is not a pixel count"),
                          ("nocol.csv", "missing column\\(s\\) \\['adv_count'\\]"),
                          ("dup.csv", "several rows for dataset our_dataset, model SegFormer-B5, class person, frame 00000"),
                          ("nope.csv", "plot.frame_counts_csv=.*nope.csv: no such file")):
        proc = run_cli(args[:2] + [f"plot.frame_counts_csv={tmp_path / name}", f"cache_dir={cache}",
                                   "tracking.enabled=false"], tmp_path)
        assert proc.returncode != 0 and re.search(message, proc.stderr), (name, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr
    proc = run_cli(args + ["plot.ranking.classes=[unicorn]"], tmp_path)
    assert proc.returncode == 2 and "plot.ranking.classes: unknown class(es) ['unicorn']" in proc.stderr
    proc = run_cli(args + ["plot.ranking.classes=[bus]"], tmp_path)  # a class, but not in the file
    assert proc.returncode != 0 and "plot.ranking.classes: ['bus'] not in" in proc.stderr
