"""Figure conventions: one naming of conditions, a xi heatmap per model with a colour bar, qualitative
grids whose colours are all explained, a progress bar over figures, and every model loaded once per run."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pairedgta.figures.qualitative as qualitative
from pairedgta.cityscapes import CLASS_NAMES, colorize
import pairedgta.figures.xi as xi_figure
import pairedgta.models as models
from pairedgta.app import run
from pairedgta.conditions import WEATHER_DISPLAY, condition_display
from pairedgta.testing.cli import compose_cfg, fast_overrides

PKG = Path(__file__).resolve().parents[1] / "pairedgta"


def test_one_naming_of_conditions():
    assert condition_display("Day-EXTRASUNNY") == "Day-Sunny"
    assert condition_display("Night-FOGGY") == "Night-Foggy"
    assert condition_display("fog_0.5") == "fog_0.5"
    from pairedgta.figures import common

    assert common.condition_display is condition_display
    # no second mapping of GTA weathers to display names anywhere in figures or stages
    for path in [*(PKG / "figures").glob("*.py"), *(PKG / "stages").glob("*.py")]:
        assert not re.search(r"[\"']EXTRASUNNY[\"']\s*:", path.read_text()), path
    assert set(WEATHER_DISPLAY) >= {"EXTRASUNNY", "RAIN", "FOGGY"}


def _xi_rows(models_: list[str], conditions: list[str], classes: list[str]) -> pd.DataFrame:
    rows = []
    rng = np.random.default_rng(0)
    for m in models_:
        for c in conditions:
            for k, cls in enumerate(classes + ["mean"]):
                rows.append({"model": m, "reference_model": "ref", "condition": c, "class_id": k if cls != "mean" else -1,
                             "class_name": cls, "xi": rng.uniform() if c != "Day-EXTRASUNNY" else 1.0})
    return pd.DataFrame(rows)


def test_xi_heatmap_is_one_conditions_by_classes_figure_per_model_with_a_colour_bar(tmp_path, monkeypatch):
    drawn = {}
    save = xi_figure.save

    def keep(fig, out, stem, formats, dpi):
        axes = fig.get_axes()
        drawn[stem] = {"n_axes": len(axes), "rows": [t.get_text() for t in axes[0].get_yticklabels()],
                       "cols": [t.get_text() for t in axes[0].get_xticklabels()], "cbar": axes[1].get_ylabel(),
                       "cells": [t.get_text() for t in axes[0].texts]}
        return save(fig, out, stem, formats, dpi)

    monkeypatch.setattr(xi_figure, "save", keep)
    conds = ["Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY"]
    frame = _xi_rows(["segformer_b5", "ddrnet_23"], conds, ["road", "car"])
    files = xi_figure.heatmap_figures(frame, "Day-EXTRASUNNY", tmp_path, ["png"], 40)
    assert {m: [p.name for p in f] for m, f in files.items()} == {
        "segformer_b5": ["xi_table_segformer_b5.png"], "ddrnet_23": ["xi_table_ddrnet_23.png"]}
    assert all(p.is_file() for f in files.values() for p in f)
    fig = drawn["xi_table_ddrnet_23"]
    assert fig["n_axes"] == 2 and fig["cbar"] == "\u03be (%)"  # heatmap + colour bar
    assert fig["rows"] == ["Day-Rain", "Night-Sunny"]  # the paper's names, the reference left out
    assert fig["cols"] == ["road", "car", "Mean"]
    part = frame[(frame.model == "ddrnet_23") & (frame.condition == "Night-EXTRASUNNY")].set_index("class_name")
    assert f"{100 * part.at['car', 'xi']:.1f}" == fig["cells"][4]  # row 2, column 2


def test_disagreement_overlay_uses_the_legend_colours():
    image = np.full((2, 3, 3), 128, dtype=np.uint8)  # dims to the legend's mid grey
    pseudo = np.array([[1, 1, 255], [2, 2, 255]])
    pred = np.array([[1, 0, 4], [2, 2, 2]])
    out = qualitative.disagreement_overlay(image, pred, pseudo).astype(float)
    legend = dict(qualitative.LEGEND)
    assert len(legend) == 3
    red = next(c for t, c in legend.items() if t.startswith("disagrees"))
    green = next(c for t, c in legend.items() if t.startswith("agrees"))
    grey = next(c for t, c in legend.items() if t.startswith("void"))
    np.testing.assert_allclose(out[0, 1], red, atol=1)
    np.testing.assert_allclose(out[0, 0], green, atol=1)
    np.testing.assert_allclose(out[0, 2], grey, atol=1)
    np.testing.assert_allclose(out[1, 2], grey, atol=1)


@pytest.mark.slow
def test_a_run_loads_each_model_once_explains_its_colours_and_shows_plot_progress(tmp_path, monkeypatch, capsys):
    built: list[str] = []
    build = models.build_model

    segmenters = {}

    def counting(model, device=None, **kw):
        built.append(dict(model)["name"] if not isinstance(model, str) else model)
        segmenters[built[-1]] = build(model, device=device, **kw)
        return segmenters[built[-1]]

    monkeypatch.setattr(models, "build_model", counting)
    grids = {}
    save = qualitative.save
    shown: dict[tuple[str, str], np.ndarray] = {}  # (group, condition) -> the image the grid loaded
    load = qualitative.load_group_images

    def loaded(group, conditions):
        images = load(group, conditions)
        shown.update({(group.group_id, c): im for c, im in images.items()})
        return images

    monkeypatch.setattr(qualitative, "load_group_images", loaded)

    def keep(fig, out, stem, formats, dpi):
        grids[stem] = {"legends": [(lg.get_title().get_text(), [t.get_text() for t in lg.get_texts()]) for lg in fig.legends],
                       "labels": [a.get_xlabel() or a.get_ylabel() for a in fig.get_axes()],
                       "strips": [a.get_images()[0].get_array() for a in fig.get_axes() if a.get_images()], "dpi": dpi}
        return save(fig, out, stem, formats, dpi)

    monkeypatch.setattr(qualitative, "save", keep)
    over = fast_overrides(tmp_path) + ["models=[tiny_segformer,tiny_pidnet]", "plot.figures=[xi_table,qualitative]",
                                       "plot.qualitative_groups=2"]  # worst and best: two groups, each in two rows
    summary = run(compose_cfg(over))
    # pseudo-labels, evaluation and the qualitative figure share one model each
    assert sorted(built) == ["tiny_pidnet", "tiny_segformer"]
    assert set(grids) == {"qualitative_tiny_segformer", "qualitative_tiny_pidnet"}
    for g in grids.values():
        (_, overlay), (title, classes) = g["legends"]
        assert overlay == [t for t, _ in qualitative.LEGEND]
        # the prediction columns' key: the classes shown, in Cityscapes order
        assert title == "predicted classes" and classes and classes == [c for c in CLASS_NAMES if c in classes]
        assert "max softmax probability" in g["labels"]  # the confidence column's colour bar
    # each row's clean-prediction column is the model's prediction of that row's clean image (a group
    # shown for several conditions is predicted once, and shown alike in each of its rows)
    rows = pd.read_csv(Path(summary["plot"]) / "qualitative.csv", dtype={"pair_id": str})
    for name in ("tiny_segformer", "tiny_pidnet"):
        strips, dpi = grids[f"qualitative_{name}"]["strips"], grids[f"qualitative_{name}"]["dpi"]
        mine = rows[rows["model"] == name].reset_index(drop=True)
        assert len(mine) == len(strips) and mine["pair_id"].nunique() > 1 and mine["pair_id"].duplicated().any(), mine
        for row, strip in zip(mine.itertuples(), strips):
            clean = shown[(row.pair_id, "Day-EXTRASUNNY")]
            h0, w0 = clean.shape[:2]
            w = max(8, min(w0, int(qualitative.TEXT_WIDTH * dpi / len(qualitative.COLUMNS))))
            gap = max(2, w // 64)
            labels, _ = segmenters[name].predict(clean[None])
            expected = qualitative.fit(colorize(labels[0].numpy()), w, strip.shape[0], exact=True)
            np.testing.assert_array_equal(np.asarray(strip)[:, w + gap: 2 * w + gap], expected)
    err = capsys.readouterr().err
    assert re.search(r"plot: 100%\|[^\n\r]*\| 2/2", err), err[-1500:]
    owners = pd.read_json(Path(summary["plot"]) / "owners.json", orient="index")
    assert sorted(owners.index) == sorted(["xi_table_tiny_segformer.png", "xi_table_tiny_pidnet.png",
                                           "qualitative_tiny_segformer.png", "qualitative_tiny_pidnet.png"])
    assert all(name.endswith(f"_{m}.png") for name, m in owners["model"].items())

    # outside a run every call builds a fresh model (nothing is kept between runs)
    built.clear()
    cfg = models.model_config("tiny_segformer")
    assert models.shared_model(cfg) is not models.shared_model(cfg)
    assert built == ["tiny_segformer", "tiny_segformer"]


@pytest.mark.slow
def test_contact_sheet_has_a_class_colour_key_for_its_label_tile(tmp_path, monkeypatch):
    import pairedgta.figures.contact_sheet as sheet

    legends = []
    save = sheet.save

    def keep(fig, out, stem, formats, dpi):
        legends.extend((lg.get_title().get_text(), [t.get_text() for t in lg.get_texts()]) for lg in fig.legends)
        return save(fig, out, stem, formats, dpi)

    monkeypatch.setattr(sheet, "save", keep)
    summary = run(compose_cfg(fast_overrides(tmp_path) + ["stages=[generate,plot]", "plot.figures=[contact_sheet]"]))
    assert (Path(summary["plot"]) / "contact_sheet.png").is_file()
    ((title, classes),) = legends
    assert title == "classes (Cityscapes colours)"
    assert len(classes) >= 3 and classes == [c for c in CLASS_NAMES if c in classes]  # road, sky, ... in order


def test_figures_that_key_the_plot_by_their_own_files_say_so_in_their_spec():
    """The plot stage reads each figure's FigureSpec instead of importing every figure module on a cached
    run: every declared function exists, and a module with a `cache_key` declares it (else its own files
    would not enter the plot stage's key)."""
    import importlib

    from pairedgta.figures import FIGURES

    assert len({spec.name for spec in FIGURES}) == len(FIGURES)
    for spec in FIGURES:
        module = importlib.import_module(spec.draw.split(":")[0])
        assert spec.drawer() is module.draw, spec.name
        assert hasattr(module, "cache_key") == (spec.key is not None), spec.name
        assert spec.keyer() is getattr(module, "cache_key", None), spec.name
        assert spec.needs in ("generate", "pseudolabel", "evaluate") if spec.source is None else spec.needs is None


def test_the_plan_reads_what_figures_need_from_their_specs():
    """needs, unless and source decide which stages run; an unknown name is one line listing the known ones."""
    from pairedgta.errors import ConfigError
    from pairedgta.figures import figures_of, needed_stages

    assert needed_stages({"plot": {"figures": ["xi_table", "distribution", "cost"]}}) == {"evaluate", "pseudolabel",
                                                                                         "generate"}
    assert needed_stages({"plot": {"figures": ["cost"]}, "cost": {"csv": "timings.csv"}}) == set()
    given = {"plot": {"figures": ["xi_table"], "table_csv": "t.csv", "frame_counts_csv": "f.csv"}}
    assert figures_of(given) == ["authors_ranking", "authors_table"] and needed_stages(given) == set()
    with pytest.raises(ConfigError, match=r"^plot.figures='nope' is unknown; choose one of: ablation, authors_ranking"):
        needed_stages({"plot": {"figures": ["nope"]}})
    with pytest.raises(ConfigError, match=r"authors_table is drawn from a file of yours; set plot.table_csv=PATH"):
        figures_of({"plot": {"figures": ["authors_table"]}})


def test_the_stage_results_provide_what_figures_read():
    """Figures read a pass through the Protocols of pairedgta/figures/inputs.py (they import no stage); the
    plot stage hands them the stages' own classes, which must provide every member."""
    from dataclasses import fields

    from pairedgta.figures import inputs
    from pairedgta.evaluation.work import EvaluateResult
    from pairedgta.stages.generate import GeneratedData
    from pairedgta.stages.planning import PassResult
    from pairedgta.evaluation.pseudolabel import PseudoLabels

    for protocol, cls in ((inputs.FigurePass, PassResult), (inputs.Evaluation, EvaluateResult),
                          (inputs.PseudoLabels, PseudoLabels), (inputs.GeneratedData, GeneratedData)):
        members = {name for name in vars(protocol) if not name.startswith("_")}
        assert len(members) >= 2, protocol
        missing = members - set(dir(cls)) - {f.name for f in fields(cls)}
        assert not missing, (protocol.__name__, cls.__name__, missing)


def test_model_colours_are_matplotlibs_palettes_and_the_mlflow_runs_use_them():
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    from pairedgta.figures.common import model_color
    from pairedgta.figures.model_colors import MODEL_ORDER, MODEL_PALETTE
    from pairedgta.tracking.naming import model_run_color

    assert list(MODEL_PALETTE) == [to_hex(c) for c in [*colormaps["tab10"].colors, *colormaps["Dark2"].colors]]
    for name in [*MODEL_ORDER, "my_own_model"]:
        assert model_run_color(name) == to_hex(model_color(name))
    zoo = ["demo_segformer", "demo_segformer_noaug", "demo_ddrnet", "demo_pidnet"]
    assert len({model_run_color(m) for m in zoo}) == len(zoo)
