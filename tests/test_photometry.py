"""Photometric calibration: the statistic on hand-made images, the checks, and the experiment end to end on a
small Blender render (2 groups, low resolution) against the GTA V bands."""
from __future__ import annotations

import types

import numpy as np
import pytest

from pairedgta.metrics.photometry import band_checks, group_rows, image_stats, physics_checks, summarise

pytestmark = pytest.mark.slow  # end to end: the CLI or the stage graph on every test


def test_luma_and_contrast_of_known_images():
    grey = np.full((4, 4, 3), 128, np.uint8)
    s = image_stats(grey)
    assert s["luma"] == pytest.approx(128 / 255) and s["contrast"] == 0.0
    half = np.zeros((2, 2, 3), np.uint8)
    half[0] = 255  # two white, two black pixels: mean 0.5, population std 0.5
    s = image_stats(half)
    assert s["luma"] == pytest.approx(0.5) and s["contrast"] == pytest.approx(0.5)
    green = np.zeros((1, 1, 3), np.float32)
    green[..., 1] = 1.0
    assert image_stats(green)["luma"] == pytest.approx(0.7152)  # Rec. 709 weight of G
    assert np.isnan(image_stats(grey, np.zeros((4, 4), bool))["luma"])


def test_ratios_are_per_group_and_summarised_by_median():
    def img(level, spread):
        a = np.full((2, 2, 3), level, np.float32)
        a[0] += spread
        return a

    groups = [("g0", {"clean": img(0.4, 0.2), "dark": img(0.04, 0.02)}, None),
              ("g1", {"clean": img(0.5, 0.2), "dark": img(0.1, 0.02)}, None),
              ("g2", {"clean": img(0.2, 0.2), "dark": img(0.1, 0.2)}, None)]
    rows = group_rows(groups, "clean")
    ratios = {r["group_id"]: r["luma_ratio"] for r in rows if r["condition"] == "dark"}
    assert ratios["g0"] == pytest.approx(0.05 / 0.5) and ratios["g2"] == pytest.approx(0.2 / 0.3)
    dark, = [r for r in summarise(rows, ["dark"])]
    assert dark["n_groups"] == 3
    assert dark["luma_ratio_median"] == pytest.approx(np.median(list(ratios.values())))
    assert dark["contrast_ratio_min"] == pytest.approx(0.1) and dark["contrast_ratio_max"] == pytest.approx(1.0)


def test_checks_name_what_fails():
    C = lambda t, w: types.SimpleNamespace(time=t, weather=w)  # noqa: E731
    conds = {"Day-EXTRASUNNY": C("Day", "EXTRASUNNY"), "Sunset-EXTRASUNNY": C("Sunset", "EXTRASUNNY"),
             "Night-EXTRASUNNY": C("Night", "EXTRASUNNY"), "Night-RAIN": C("Night", "RAIN")}
    row = lambda n, lum, ratio, sky: {"condition": n, "luma_median": lum, "luma_ratio_median": ratio,  # noqa: E731
                                      "sky_luma_median": sky}
    summary = [row("Day-EXTRASUNNY", 0.4, 1.0, 0.7), row("Sunset-EXTRASUNNY", 0.2, 0.5, 0.3),
               row("Night-EXTRASUNNY", 0.05, 0.12, 0.05), row("Night-RAIN", 0.06, 0.4, 0.2)]
    checks = {c["check"]: c["ok"] for c in physics_checks(summary, conds, "Day-EXTRASUNNY")}
    assert checks["Night-EXTRASUNNY: luma ratio <= 0.35"] and not checks["Night-RAIN: luma ratio <= 0.35"]
    assert not checks["Night-RAIN: sky luma < 0.15"] and not checks["Night-RAIN: luma <= Night-EXTRASUNNY"]
    assert checks["EXTRASUNNY: luma Day > Sunset > Night"]
    bands = band_checks([{"condition": "Night-RAIN", "luma_ratio_median": 0.4, "contrast_ratio_median": 0.1}],
                        {"Night-RAIN": {"luma_ratio": [0.08, 0.25], "contrast_ratio": [0.06, 0.35]}})
    assert [c["ok"] for c in bands] == [False, True]


def test_a_light_ladder_must_darken_step_by_step():
    from pairedgta.metrics.photometry import ladder_checks

    row = lambda n, v: {"condition": n, "luma_ratio_median": v}  # noqa: E731
    good = [row("clean", 1.0), row("a", 0.6), row("b", 0.61), row("c", 0.2)]
    assert [c["ok"] for c in ladder_checks(good, ["clean", "a", "b", "c"])] == [True, True]
    rising = [row("clean", 1.0), row("a", 0.3), row("b", 0.4)]
    assert [c["ok"] for c in ladder_checks(rising, ["clean", "a", "b"])] == [False, False]


def test_the_calibration_experiment_meets_the_gta_bands(calibration):
    """The main job's 8 scenes at 128x64, one sample: every check of the calibration passes (the bands are
    medians over groups of a ratio of means, which the resolution barely moves: Night-RAIN luma / contrast and
    Sunset-FOGGY luma / contrast 0.106 / 0.129 / 0.517 / 0.491 here against 0.110 / 0.158 / 0.520 / 0.466 at
    512x256). Two groups would not do: the two first scenes alone are darker than the median."""
    table, checks, folder = calibration(8)
    assert table.loc["Day-EXTRASUNNY", "luma_ratio_median"] == pytest.approx(1.0)
    assert table.loc["Night-RAIN", "gta_luma_ratio_median"] == pytest.approx(0.1232)
    assert len(checks) == 16 and checks["ok"].all(), checks[~checks["ok"]].to_string()
    assert checks["check"].str.contains("GTA V band").sum() == 4
    assert (folder / "photometry.png").is_file()
