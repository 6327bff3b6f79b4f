"""experiments/measure_gta_photometry.py on a synthetic figure with known panels and statistics, and the
shipped measurement (pairedgta/data/gta_photometry.csv) it produced from the authors' qualitative figures."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from pairedgta.data import DATA_DIR

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "measure_gta_photometry.py"
GTA_PHOTOMETRY = DATA_DIR / "gta_photometry.csv"

# synthetic figure: 2 rows x 3 panels [clean photo, label map, adverse photo] on white, with title-like marks
W, H, LEFT, TOP, GAP_X, GAP_Y, FRAME = 200, 100, 20, 40, 30, 60, 3
PHOTOS = {  # row -> (clean top half, clean bottom half, adverse top half, adverse bottom half)
    0: ((250, 250, 250), (40, 80, 120), (10, 12, 20), (30, 20, 5)),    # near-white "sky" over a dark road
    1: ((180, 160, 140), (90, 100, 110), (120, 90, 130), (60, 70, 80)),
}
ROAD, SKY = (128, 64, 128), (70, 130, 180)  # Cityscapes palette colours


def load_script():
    spec = importlib.util.spec_from_file_location("measure_gta_photometry", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def luma(c) -> float:
    r, g, b = (v / 255 for v in c)
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def box(row: int, col: int) -> tuple[int, int, int, int]:
    y0, x0 = TOP + row * (H + GAP_Y), LEFT + col * (W + GAP_X)
    return y0, y0 + H, x0, x0 + W


def photo(top, bottom) -> np.ndarray:
    """Top and bottom halves in two colours inside a 3 px grey frame (which the statistics must skip)."""
    p = np.empty((H, W, 3), np.uint8)
    p[: H // 2], p[H // 2:] = top, bottom
    p[:FRAME], p[-FRAME:], p[:, :FRAME], p[:, -FRAME:] = 128, 128, 128, 128
    return p


def write_figure(path: Path) -> None:
    fig = np.full((TOP + 2 * (H + GAP_Y), 2 * LEFT + 3 * W + 2 * GAP_X, 3), 255, np.uint8)
    fig[5, 10:-10] = 0                             # a one-pixel rule across most of the width: not a panel band
    for row, (ct, cb, at, ab) in PHOTOS.items():
        for col in range(3):
            y0, y1, x0, x1 = box(row, col)
            fig[y0 - 15:y0 - 10, x0 + 70:x0 + 130] = 0   # a title above each panel
        label = np.empty((H, W, 3), np.uint8)
        label[: H // 3], label[H // 3:] = SKY, ROAD
        label[H // 3, ::7] = (100, 100, 100)       # a few blended edge pixels that are not palette colours
        for col, panel in enumerate((photo(ct, cb), label, photo(at, ab))):
            y0, y1, x0, x1 = box(row, col)
            fig[y0:y1, x0:x1] = panel
    rgba = np.dstack([fig, np.full(fig.shape[:2], 255, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(path)


@pytest.fixture(scope="module")
def script():
    return load_script()


@pytest.fixture
def figure(tmp_path: Path) -> Path:
    path = tmp_path / "qual_test_clean_vs_Night-RAIN.png"
    write_figure(path)
    return path


def test_panel_grid_is_found_from_the_gutters(script, figure):
    grid = script.find_panels(script.load_rgb(figure))
    assert grid == [[box(row, col) for col in range(3)] for row in range(2)]


def test_statistics_of_the_photo_panels(script, figure):
    groups = script.measure_figure(figure)
    assert [g["row"] for g in groups] == [0, 1]
    for g in groups:
        ct, cb, at, ab = PHOTOS[g["row"]]
        assert g["condition"] == "Night-RAIN" and g["file"] == figure.name
        clean_luma, adverse_luma = (luma(ct) + luma(cb)) / 2, (luma(at) + luma(ab)) / 2
        clean_contrast, adverse_contrast = abs(luma(ct) - luma(cb)) / 2, abs(luma(at) - luma(ab)) / 2
        assert g["clean_luma"] == pytest.approx(clean_luma, abs=1e-9)
        assert g["adverse_luma"] == pytest.approx(adverse_luma, abs=1e-9)
        assert g["clean_contrast"] == pytest.approx(clean_contrast, abs=1e-9)
        assert g["adverse_contrast"] == pytest.approx(adverse_contrast, abs=1e-9)
        assert g["luma_ratio"] == pytest.approx(adverse_luma / clean_luma, rel=1e-9)
        assert g["contrast_ratio"] == pytest.approx(adverse_contrast / clean_contrast, rel=1e-9)
        for i, ch in enumerate("rgb"):
            assert g[f"adverse_{ch}"] == pytest.approx((at[i] + ab[i]) / 2 / 255, abs=1e-9)
            assert g[f"clean_{ch}"] == pytest.approx((ct[i] + cb[i]) / 2 / 255, abs=1e-9)
        assert g["clean_box"] == "y{}:{} x{}:{}".format(*box(g["row"], 0))
        assert g["adverse_box"] == "y{}:{} x{}:{}".format(*box(g["row"], 2))


def test_cli_writes_the_summary(script, figure, tmp_path):
    out, groups = tmp_path / "summary.csv", tmp_path / "groups.csv"
    assert script.main(["--figures", str(figure.parent), "--out", str(out), "--groups", str(groups)]) == 0
    s, g = pd.read_csv(out), pd.read_csv(groups)
    assert list(s.columns) == script.SUMMARY_COLUMNS and len(g) == 2
    (row,) = s.to_dict("records")
    assert row["condition"] == "Night-RAIN" and row["n_groups"] == 2 and row["source_files"] == figure.name
    assert row["luma_ratio_median"] == pytest.approx(g["luma_ratio"].median(), abs=1e-4)
    assert row["contrast_ratio_min"] == pytest.approx(g["contrast_ratio"].min(), abs=1e-4)


def test_shipped_gta_photometry():
    d = pd.read_csv(GTA_PHOTOMETRY).set_index("condition")
    assert {"Night-RAIN", "Sunset-FOGGY"} <= set(d.index)
    for cond, r in d.iterrows():
        assert r["n_groups"] > 0 and r["source_files"] and r["method"], cond
        for stat in ("luma_ratio", "contrast_ratio"):
            assert 0 < r[f"{stat}_min"] <= r[f"{stat}_median"] <= r[f"{stat}_max"], (cond, stat)
        assert 0 <= r["adverse_luma_median"] <= 1 and 0 <= r["clean_luma_median"] <= 1, cond
    assert d.loc["Night-RAIN", "luma_ratio_median"] < d.loc["Sunset-FOGGY", "luma_ratio_median"] < 1
