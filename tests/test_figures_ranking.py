"""Ranking figure: a class without rho_valid is explained in words, not drawn as a black heatmap."""
from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import pandas as pd  # noqa: E402

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
