"""The paper's experiments end to end on tiny data (random-init tiny models, 64x32 synthetic scenes, a
synthetic ACDC tree with ACDC's file naming): every figure and table exists and holds the numbers of the
metric functions, recomputed here independently where it is cheap."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from pairedgta.app import run
from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX
from pairedgta.datasets.acdc import REFERENCE, open_acdc
from pairedgta.testing.acdc import write_standin
from pairedgta.errors import ConfigError, DataError
from pairedgta.metrics import prediction_mass, rho_valid
from pairedgta.models import build_model
from pairedgta.testing.cli import compose_cfg, fast_overrides, mlflow_store, run_cli

TINY = ["models=[tiny_segformer,tiny_mask2former]", "reference_model=tiny_segformer"]


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """One cache for the module: experiments share the generated dataset and its pseudo-labels."""
    return tmp_path_factory.mktemp("experiments")


def base(work: Path) -> list[str]:
    return fast_overrides(work) + ["generate.num_scenes=4"]


def png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


# -- Table 1 -----------------------------------------------------------------------------------
def parse_markdown_tables(text: str) -> dict[str, tuple[list[str], dict[str, list[str]]]]:
    """'## Day-Sunny → Day-Rain' sections -> (header, {model: cells})."""
    out = {}
    for section in re.split(r"^## ", text, flags=re.MULTILINE)[1:]:
        title, *lines = section.strip().splitlines()
        rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines if line.startswith("|")]
        header, body = rows[0], rows[2:]
        out[title.split("\u2192")[1].strip()] = (header[1:], {r[0]: r[1:] for r in body})
    return out


def parse_latex_tables(text: str) -> dict[str, dict[str, list[str]]]:
    out = {}
    for block in text.split("\\begin{subtable}")[1:]:
        cond = re.search(r"\$\\rightarrow\$ (.+?)\.\}", block).group(1)
        body = block.split("\\midrule")[1].split("\\bottomrule")[0]
        rows = [[c.strip() for c in line.rstrip("\\ ").split("&")] for line in body.strip().splitlines()]
        out[cond] = {r[0].replace("\\_", "_"): r[1:] for r in rows}
    return out


def cell_value(cell: str) -> tuple[float, bool]:
    bold = cell.startswith(("**", "\\textbf"))
    m = re.search(r"-?\d+\.\d", cell)
    return (float(m.group(0)) if m else math.nan), bold


def check_table(plot_dir: Path, evals: dict[str, Path], reference: str = "Day-EXTRASUNNY") -> None:
    xi = pd.concat([pd.read_csv(p / "xi.csv") for p in evals.values()])
    xi = xi[(xi.reference_model != "ground_truth") & (xi.condition != reference)]
    md = parse_markdown_tables((plot_dir / "table1_xi.md").read_text())
    tex = parse_latex_tables((plot_dir / "table1_xi.tex").read_text())
    wide = pd.read_csv(plot_dir / "table1_xi.csv")
    display = {"Day-RAIN": "Day-Rain", "Night-EXTRASUNNY": "Night-Sunny"}
    assert set(md) == set(tex) == {display[c] for c in set(xi.condition)}
    for cond, shown in display.items():
        part = xi[xi.condition == cond]
        # the classes the convention's mean covers for some model (paper: the 17 of Table 1, absent ones
        # as 0; strict: those with pseudo-label pixels)
        classes = [c for c in CLASS_NAMES if part[(part.class_name == c)].in_mean.any()]
        header, rows = md[shown]
        short = {"traffic light": "T. light", "traffic sign": "T. sign", "motorcycle": "motor."}
        assert header == [short.get(c, c) for c in classes] + ["Mean"]
        # the reference model is scored on its own pseudo-labels: named so, and never bold
        own = set(part.loc[part.model == part.reference_model, "model"])
        assert {m for m in rows if m.endswith(" (reference, not ranked)")} == {f"{m} (reference, not ranked)" for m in own}
        rows = {m.replace(" (reference, not ranked)", ""): r for m, r in rows.items()}
        tex[shown] = {m.replace(" (reference, not ranked)", ""): r for m, r in tex[shown].items()}
        assert set(rows) == set(evals) == set(tex[shown])
        paper = (part.convention == "paper").all()
        for j, cls in enumerate(classes + ["mean"]):
            expected = {m: round(float(part[(part.model == m) & (part.class_name == cls)].xi.iloc[0]) * 100, 1) for m in evals}
            if cls == "mean" and paper:  # the authors' Mean: the mean of the printed cells
                cells = part[(part.class_name != "mean") & part.in_mean]
                expected = {m: round(cells[cells.model == m].xi.mul(100).round(1).mean(), 1) for m in evals}
            shown_md = {m: cell_value(rows[m][j]) for m in evals}
            shown_tex = {m: cell_value(tex[shown][m][j]) for m in evals}
            best = max((v for m, v in expected.items() if not math.isnan(v) and m not in own), default=None)
            for m in evals:
                if math.isnan(expected[m]):
                    assert math.isnan(shown_md[m][0]) and not shown_md[m][1]
                    continue
                assert shown_md[m][0] == pytest.approx(expected[m]) and shown_tex[m][0] == pytest.approx(expected[m])
                assert shown_md[m][1] == shown_tex[m][1] == (m not in own and expected[m] == best), (cond, cls, m)
            csv_vals = wide[wide.condition == cond].set_index("model")[cls]
            for m in evals:
                exact = float(part[(part.model == m) & (part.class_name == cls)].xi.iloc[0])
                tol = None
                if cls == "mean" and paper:  # printed to one decimal
                    cells = part[(part.class_name != "mean") & part.in_mean & (part.model == m)]
                    exact, tol = cells.xi.mul(100).round(1).mean() / 100, 5e-4 + 1e-9
                assert (math.isnan(exact) and math.isnan(csv_vals[m])) or csv_vals[m] == pytest.approx(exact, abs=tol)
    assert "\\toprule" in (plot_dir / "table1_xi.tex").read_text() and "\\bottomrule" in (plot_dir / "table1_xi.tex").read_text()


@pytest.mark.slow
def test_paper_table_one_run_qualitative_and_multirun_aggregate(work):
    s = run(compose_cfg(base(work) + TINY + ["+experiment=paper_table"]))
    plot_dir = Path(s["plot"])
    evals = {m: Path(p) for m, p in s["evaluate"].items()}
    assert {"table1_xi.md", "table1_xi.tex", "table1_xi.csv"} <= {p.name for p in plot_dir.iterdir()}
    assert {f"xi_table_{m}.png" for m in evals} <= {p.name for p in plot_dir.iterdir()}  # a heatmap per model
    check_table(plot_dir, evals)

    # qualitative grids: the worst and the best group per condition by the cached per-image agreement,
    # predicted again in the plot stage with the same result
    q = pd.read_csv(plot_dir / "qualitative.csv", dtype={"pair_id": str})
    for model, path in evals.items():
        assert (plot_dir / f"qualitative_{model}.png").is_file()
        agree = pd.read_csv(path / "pixel_agreement.csv", dtype={"pair_id": str})
        for cond in ("Day-RAIN", "Night-EXTRASUNNY"):
            a = agree[(agree.condition == cond) & (agree.pair_id != "ALL")].dropna(subset=["agreement_reference"])
            picked = q[(q.model == model) & (q.condition == cond)].set_index("kind")
            assert picked.loc["worst", "agreement"] == pytest.approx(a.agreement_reference.min())
            assert picked.loc["best", "agreement"] == pytest.approx(a.agreement_reference.max())
        np.testing.assert_allclose(q[q.model == model].agreement_recomputed, q[q.model == model].agreement, atol=1e-6)

    # multirun aggregate: another model evaluated alone, then a plot-only run collects every cached
    # evaluation of the same dataset and pseudo-labels (and skips the model that was never evaluated)
    single = run(compose_cfg(base(work) + ["+experiment=paper_table", "models=null", "model=tiny_ddrnet",
                                          "reference_model=tiny_segformer"]))
    evals["tiny_ddrnet"] = Path(single["evaluate"]["tiny_ddrnet"])
    agg = run(compose_cfg(base(work) + ["+experiment=paper_table", "models=null", "model=tiny_pidnet",
                                       "reference_model=tiny_segformer", "stages=[plot]", "plot.figures=[xi_table]"]))
    assert agg["evaluate"] == {}
    check_table(Path(agg["plot"]), evals)


# -- pseudo-label distribution -------------------------------------------------------------------
@pytest.mark.slow
def test_pseudo_label_distribution(work):
    s = run(compose_cfg(base(work) + TINY + ["+experiment=pseudo_label_distribution"]))
    out, pseudo = Path(s["plot"]), Path(s["pseudolabel"])
    assert (out / "pseudo_label_distribution.png").is_file()
    labels = {p.stem: png(p) for p in sorted((pseudo / "labels").glob("*.png"))}
    counts = np.bincount(np.concatenate([l[l != IGNORE_INDEX].ravel() for l in labels.values()]).astype(int), minlength=19)
    mass = pd.read_csv(out / "pixel_mass.csv")
    assert mass.class_name.tolist() == list(CLASS_NAMES) and mass.pixels.tolist() == counts.tolist()
    np.testing.assert_allclose(mass.percent_of_valid, 100 * counts / counts.sum())
    # the example is the group whose pseudo-label keeps the most pixels
    best = max(labels, key=lambda g: ((labels[g] != IGNORE_INDEX).sum(), [-ord(ch) for ch in g]))
    metrics = json.loads((out / "metrics.json").read_text())
    void = 1 - sum((l != IGNORE_INDEX).sum() for l in labels.values()) / sum(l.size for l in labels.values())
    assert metrics["pseudo_label/generated/void_share"] == pytest.approx(void)
    from pairedgta.figures.distribution import example_group
    from pairedgta.evaluation.pseudolabel import PseudoLabels

    assert example_group(PseudoLabels("pseudolabel", pseudo.name, pseudo, hit=True), None) == best


# -- ACDC and night_vs_acdc ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def acdc_root(work) -> Path:
    """ACDC's tree and file names, filled from a coarsely paired synthetic run (not ACDC itself)."""
    s = run(compose_cfg(fast_overrides(work / "standin") + [
        "stages=[generate]", "generate.num_scenes=6", "generate.drop_invalid=false",
        "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]",
        "+generate.pairing={camera_jitter_m: 1.0, camera_jitter_deg: 3.0, object_resample_prob: 1.0}"]))
    root = write_standin(s["dataset"], work / "ACDC", "Day-EXTRASUNNY", "Night-EXTRASUNNY", val_share=0.34)
    # one adverse frame without its reference, one without ground truth
    ref = next((root / "rgb_anon/night/train_ref").glob("*/*_frame_000001_rgb_ref_anon.png"))
    ref.unlink()
    next((root / "gt/night/train").glob("*/*_frame_000002_gt_labelTrainIds.png")).unlink()
    return root


@pytest.mark.slow
def test_acdc_reader_layout_missing_reference_and_bad_root(acdc_root, tmp_path, caplog):
    ds = open_acdc(condition="night", splits=["train", "val"], name="acdc", root=acdc_root)
    grid = ds.grid
    assert grid.names == [REFERENCE, "ACDC-night"] and grid.reference == REFERENCE
    assert len(ds) == 5 and ds.skipped_without_reference == 1 and "without their reference" in caplog.text
    assert [g.group_id.split("_")[0] for g in ds.groups] == ["train"] * 3 + ["val"] * 2
    g = ds.groups[0]
    assert g.images[REFERENCE].name.endswith("_rgb_ref_anon.png") and g.images["ACDC-night"].name.endswith("_rgb_anon.png")
    # ground truth belongs to the adverse frame only
    assert all(set(g.labels) <= {"ACDC-night"} for g in ds.groups)
    assert sum(bool(g.labels) for g in ds.groups) == 4
    val_only = open_acdc(condition="night", splits="val", root=acdc_root)
    assert len(val_only) == 2
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"rgb_anon/night/train.*missing; expected .*_frame_<n>_rgb_anon\.png"):
        open_acdc(condition="night", root=tmp_path / "empty")
    with pytest.raises(ConfigError, match="fog, night, rain, snow"):
        open_acdc(condition="hail", root=acdc_root)


@pytest.mark.slow
def test_night_vs_acdc(work, acdc_root):
    s = run(compose_cfg(base(work) + TINY + ["+experiment=night_vs_acdc", f"acdc.root={acdc_root}",
                                            "metric.rho.m=3"]))
    out = Path(s["plot"])
    assert {"ranking.png", "rho_valid.csv", "rho_valid.md", "qualitative_acdc_tiny_segformer.png",
            "qualitative_pairedgta_tiny_mask2former.png"} <= {p.name for p in out.iterdir()}
    table = pd.read_csv(out / "rho_valid.csv")
    assert set(zip(table.dataset_label, table.condition)) == {("PairedGTA", "Night-EXTRASUNNY"), ("ACDC", "ACDC-night")}
    assert set(table.class_name) == {"person", "car"} and set(table.selection) == {"top_m", "nonzero"}

    # phi and rho_valid on ACDC recomputed from the images with the metric functions
    ds = open_acdc(condition="night", splits=["train", "val"], root=acdc_root)
    model = build_model("tiny_segformer")
    clean, adverse = {"person": [], "car": []}, {"person": [], "car": []}
    inter, union = np.zeros(19), np.zeros(19)
    for g in ds.groups:
        probs = model.predict_proba(np.stack([png(g.images[REFERENCE]), png(g.images["ACDC-night"])]))
        for cls, k in (("person", 11), ("car", 13)):
            clean[cls].append(int(prediction_mass(probs[0], k, 0.9)))
            adverse[cls].append(int(prediction_mass(probs[1], k, 0.9)))
        if "ACDC-night" in g.labels:
            gt, pred = png(g.labels["ACDC-night"]).astype(int), probs[1].argmax(0).numpy()
            valid = gt != IGNORE_INDEX
            for c in range(19):
                inter[c] += ((gt == c) & (pred == c) & valid).sum()
                union[c] += (((gt == c) | (pred == c)) & valid).sum()
    acdc = table[(table.dataset_label == "ACDC") & (table.model == "tiny_segformer")]
    ev = Path(s["evaluate"]["ACDC/tiny_segformer"])
    counts = pd.read_csv(ev / "frame_counts.csv", dtype={"pair_id": str})
    assert sorted(set(counts.pair_id)) == sorted(g.group_id for g in ds.groups)
    for cls in ("person", "car"):
        c = counts[counts.class_name == cls].set_index("pair_id").loc[[g.group_id for g in ds.groups]]
        assert c.clean_count.tolist() == clean[cls] and c.adv_count.tolist() == adverse[cls]
        for sel in ("top_m", "nonzero"):
            got = acdc[(acdc.class_name == cls) & (acdc.selection == sel)].rho.item()
            want = rho_valid(clean[cls], adverse[cls], m=3, selection=sel)
            assert (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want, abs=1e-12)
    md = (out / "rho_valid.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| ACDC | ACDC-night | tiny_segformer"))
    for cell, (cls, sel) in zip(row.strip("| ").split(" | ")[3:], [(c, s) for c in ("person", "car") for s in ("top_m", "nonzero")]):
        r = acdc[(acdc.class_name == cls) & (acdc.selection == sel)].iloc[0]
        few = "\u2021" if r.n_frames < r.min_frames else ""  # below metric.rho.min_frames: no headline
        assert cell == ("–" if math.isnan(r.rho) else f"{r.rho:.3f}") + f" (n={int(r.n_frames)}{few})"

    # ACDC's ground truth is the night frame's: IoU for ACDC-night only, never xi against the reference
    xi = pd.read_csv(ev / "xi.csv")
    assert "ground_truth" not in set(xi.reference_model)
    iou = pd.read_csv(ev / "gt_iou.csv")
    assert set(iou.condition) == {"ACDC-night"}
    with np.errstate(invalid="ignore", divide="ignore"):
        expected = np.where(union > 0, inter / union, np.nan)
    np.testing.assert_allclose(iou[iou.class_id >= 0].sort_values("class_id").iou, expected, equal_nan=True)
    # no reference truth on ACDC, so no pseudo-label quality against it
    pseudo_acdc = json.loads((ev / "manifest.json").read_text())["inputs"]["pseudolabel"]
    assert not (work / "cache" / "pseudolabel" / pseudo_acdc / "quality.csv").exists()


@pytest.mark.slow
def test_night_vs_acdc_with_detectors(work, acdc_root):
    """task=detection: phi of a frame is the number of the model's boxes of the class scored >= its threshold; the
    counts and rho_valid recomputed here from the stored COCO results, ACDC's boxes read from its panoptic labels."""
    from pairedgta.detection.boxes import INSTANCE_CLASSES
    from pairedgta.detection.real_boxes import read_acdc_boxes

    s = run(compose_cfg(base(work) + ["task=detection", "+experiment=night_vs_acdc", f"acdc.root={acdc_root}",
                                      "metric.rho.m=3", "models=[tiny_fcos,tiny_fasterrcnn]",
                                      "reference_model=tiny_fcos"]))
    out = Path(s["plot"])
    assert {"ranking.png", "rho_valid.csv", "rho_valid.md"} <= {p.name for p in out.iterdir()}
    table = pd.read_csv(out / "rho_valid.csv")
    assert set(zip(table.dataset_label, table.condition)) == {("PairedGTA", "Night-EXTRASUNNY"), ("ACDC", "ACDC-night")}
    assert set(table.model) == {"tiny_fcos", "tiny_fasterrcnn"} and set(table.class_name) == {"person", "car"}
    ds = open_acdc(condition="night", splits=["train", "val"], root=acdc_root)
    nonzero = 0
    for model in ("tiny_fcos", "tiny_fasterrcnn"):
        ev = Path(s["evaluate"][f"ACDC/{model}"])
        threshold = json.loads((ev / "summary.json").read_text())["score_threshold"]
        counts = pd.read_csv(ev / "detection_frame_counts.csv", dtype={"pair_id": str})
        assert sorted(set(counts.pair_id)) == sorted(g.group_id for g in ds.groups)
        for cls in ("person", "car"):
            want = {}
            for cond, col in ((REFERENCE, "clean_count"), ("ACDC-night", "adv_count")):
                dets = json.loads((ev / "detections" / f"{cond}.json").read_text())
                per_image = [sum(1 for d in dets if d["image_id"] == i and d["score"] >= threshold
                                 and d["category_id"] == INSTANCE_CLASSES.index(cls) + 1)
                             for i in range(1, len(ds.groups) + 1)]
                want[col] = per_image
            c = counts[counts.class_name == cls].set_index("pair_id").loc[[g.group_id for g in ds.groups]]
            assert c.clean_count.tolist() == want["clean_count"] and c.adv_count.tolist() == want["adv_count"]
            nonzero += sum(want["clean_count"]) + sum(want["adv_count"])
            rows = table[(table.dataset_label == "ACDC") & (table.model == model) & (table.class_name == cls)]
            for sel in ("top_m", "nonzero"):
                got = rows[rows.selection == sel].rho.item()
                expected = rho_valid(want["clean_count"], want["adv_count"], m=3, selection=sel)
                assert (math.isnan(got) and math.isnan(expected)) or got == pytest.approx(expected, abs=1e-12)
    assert nonzero > 0  # the check above compared counts, not only zeros
    # ACDC's boxes are the night frame's, from gt_panoptic: ground truth for ACDC-night only, as the reader gives it
    labels = Path(s["evaluate"]["ACDC/tiny_fcos"])
    pseudo = json.loads((labels / "manifest.json").read_text())["inputs"]["pseudolabel"]
    gt_dir = work / "cache" / "pseudolabel" / pseudo / "ground_truth"
    assert [p.name for p in gt_dir.iterdir()] == ["ACDC-night.json"]
    gt = json.loads((gt_dir / "ACDC-night.json").read_text())
    g = ds.groups[0]
    png_path = g.instances["ACDC-night"]
    split = g.group_id.split("_")[0]
    boxes = read_acdc_boxes(png_path, acdc_root / "gt_panoptic" / "night" / f"night_{split}_gt_panoptic.json",
                            g.images["ACDC-night"].name)
    first = [a for a in gt["annotations"] if a["image_id"] == 1]
    assert boxes and len(first) == len(boxes)
    assert sorted(tuple(a["bbox"]) for a in first) == sorted(
        (b.xyxy[0], b.xyxy[1], b.xyxy[2] - b.xyxy[0], b.xyxy[3] - b.xyxy[1]) for b in boxes)


@pytest.mark.slow
def test_missing_acdc_root_is_a_one_line_cli_error(tmp_path):
    proc = run_cli(["+experiment=night_vs_acdc", "models=[tiny_segformer]", "reference_model=tiny_segformer",
                    f"cache_dir={tmp_path / 'cache'}", "tracking.enabled=false"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "https://acdc.vision.ee.ethz.ch" in errors[0] and "acdc.root=" in errors[0]
    assert "Traceback" not in proc.stderr and not (tmp_path / "cache" / "generate").exists()


# -- cost analysis -------------------------------------------------------------------------------
@pytest.mark.slow
def test_cost_analysis_cli_with_mlflow(tmp_path):
    db = tmp_path / "mlflow.db"
    proc = run_cli(["+experiment=cost_analysis", "renderer=synthetic", "region=synthetic_street",
                    f"cache_dir={tmp_path / 'cache'}", f"tracking.uri={mlflow_store(db)}",
                    "generate.num_scenes=4", "renderer.width=64", "renderer.height=32",
                    "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]", "plot.dpi=60"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = next(p for p in (tmp_path / "cache" / "plot").iterdir() if not p.name.startswith("."))
    assert {"cost.png", "cost.pdf", "cost_summary.csv", "cost_summary.md"} <= {p.name for p in out.iterdir()}
    summary = pd.read_csv(out / "cost_summary.csv").set_index("source")
    paper = summary.loc["paper (GTA V, RTX 2080)"]
    # the paper's numbers: 29.8 s pipeline, 6.1 s construction (20.5%), 23.7 s rendering, 4.0 s overhead, 33.8 s total
    assert round(paper.pipeline_mean_s, 1) == 29.8 and round(paper.semantic_scene_construction_mean_s, 1) == 6.1
    assert round(paper.condition_wise_rendering_mean_s, 1) == 23.7 and round(paper.overhead_mean_s, 1) == 4.0
    assert round(paper.total_mean_s, 1) == 33.8 and round(100 * paper.semantic_scene_construction_share, 1) == 20.5
    timings = pd.read_csv(next((tmp_path / "cache" / "generate").glob("[!.]*")) / "timings.csv")
    own = summary.loc["this run (synthetic)"]
    assert own.scenes == 4
    for col in ("pipeline", "overhead", "total"):
        assert own[f"{col}_mean_s"] == pytest.approx(timings[f"{col}_time"].mean())
    assert own.condition_wise_rendering_mean_s == pytest.approx(timings.condition_wise_rendering_time.mean())

    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{db}")
    (parent,) = client.search_runs([client.get_experiment_by_name("cost_analysis").experiment_id])
    arts = {a.path for a in client.list_artifacts(parent.info.run_id, "figures")}
    assert {"figures/cost.png", "figures/cost.pdf", "figures/cost_summary.md"} <= arts
    assert parent.data.metrics["cost/paper/pipeline_mean_s"] == pytest.approx(paper.pipeline_mean_s)
    assert parent.data.metrics["cost/run/total_mean_s"] == pytest.approx(timings.total_time.mean())


@pytest.mark.slow
def test_cost_from_any_csv_says_what_it_derives(tmp_path):
    from pairedgta.data import PAPER_GENERATION_TIMES
    from pairedgta.figures.cost import load_timings, summary

    df = pd.read_csv(PAPER_GENERATION_TIMES)
    g = df.global_time.to_numpy()
    first = np.r_[True, np.diff(g) < 0]
    total = np.where(first, g, g - np.r_[0, g[:-1]])
    t = load_timings(PAPER_GENERATION_TIMES, "paper")
    np.testing.assert_allclose(t.frame.total_time, total)
    np.testing.assert_allclose(t.frame.overhead_time, total - df.pipeline_time)
    assert "global_time" in t.notes[0] and "3 session(s)" in t.notes[0]
    df.drop(columns=["global_time"]).to_csv(tmp_path / "no_wall.csv", index=False)
    t = load_timings(tmp_path / "no_wall.csv", "x")
    assert math.isnan(summary(t)["overhead_mean_s"]) and "not derivable" in t.notes[0]
    with pytest.raises(DataError, match="missing timing column"):
        df.drop(columns=["pipeline_time"]).to_csv(tmp_path / "bad.csv", index=False)
        load_timings(tmp_path / "bad.csv", "x")
    # cost.csv replaces this run's generate timings: no generate stage at all
    s = run(compose_cfg(fast_overrides(tmp_path) + ["+experiment=cost_analysis", "stages=[plot]",
                                                   f"cost.csv={tmp_path / 'no_wall.csv'}", "cost.label=mine"]))
    assert s["dataset"] is None and not (tmp_path / "cache" / "generate").exists()
    summ = pd.read_csv(Path(s["plot"]) / "cost_summary.csv")
    assert summ.source.tolist() == ["paper (GTA V, RTX 2080)", "mine"]


# -- pairing ablation ----------------------------------------------------------------------------
def test_perturbation_of_the_descriptor():
    from omegaconf import OmegaConf

    from pairedgta import schema
    from pairedgta.scene.sampling import build_region
    from pairedgta.stages.generate import build_descriptor, perturb_descriptor, placement

    def pairing_config(gen):
        return schema.parse({"generate": gen}).generate.pairing

    cfg = OmegaConf.to_container(compose_cfg([]), resolve=True)
    cfg["generate"]["objects"].update(min=3, max=3)
    gen = schema.parse(cfg).generate
    region = build_region(cfg["region"])
    d, _ = build_descriptor(1, gen, region)
    pc = placement(gen)
    zero = pairing_config({})
    assert perturb_descriptor(d, "Night-EXTRASUNNY", zero, pc, region).objects == d.objects
    p = pairing_config({"pairing": {"camera_jitter_m": 0.5, "camera_jitter_deg": 2.0, "object_resample_prob": 1.0}})
    a = perturb_descriptor(d, "Night-EXTRASUNNY", p, pc, region)
    assert a == perturb_descriptor(d, "Night-EXTRASUNNY", p, pc, region)  # seeded by (scene seed, condition)
    assert a.camera != perturb_descriptor(d, "Day-RAIN", p, pc, region).camera
    for axis in ("x", "y", "z"):
        assert 0 < abs(getattr(a.camera, axis) - getattr(d.camera, axis)) <= 0.5
    for axis in ("rot_x", "rot_y", "rot_z"):
        assert 0 < abs(getattr(a.camera, axis) - getattr(d.camera, axis)) <= 2.0
    assert (a.seed, a.scene_id, a.location) == (d.seed, d.scene_id, d.location)
    assert not {(o.forward, o.right) for o in a.objects} & {(o.forward, o.right) for o in d.objects}
    moved = perturb_descriptor(d, "x", pairing_config({"pairing": {"object_move_m": 1.0}}), pc, region)
    assert [o.category for o in moved.objects] == [o.category for o in d.objects]
    assert all(abs(m.forward - o.forward) <= 1.0 and abs(m.right - o.right) <= 1.0 for m, o in zip(moved.objects, d.objects))
    with pytest.raises(ConfigError, match="object_resample_prob"):
        pairing_config({"pairing": {"object_resample_prob": 1.5}})
    with pytest.raises(ConfigError, match="generate.pairing.jitter is not a key of generate.pairing"):
        pairing_config({"pairing": {"jitter": 1}})


@pytest.mark.slow
def test_pairing_ablation(work):
    only = "conditions.only=[Day-EXTRASUNNY,Day-EXTRASUNNY-repeat]"
    s = run(compose_cfg(base(work) + ["+experiment=pairing_ablation", "models=[tiny_segformer]",
                                     "reference_model=tiny_segformer", only, "generate.num_scenes=3"]))
    out = Path(s["plot"])
    assert {"pairing_ablation.png", "pairing_ablation.csv", "pairing_ablation.md"} <= {p.name for p in out.iterdir()}
    frame = pd.read_csv(out / "pairing_ablation.csv")
    assert frame.label.tolist() == ["perfect", "mild", "moderate", "coarse"]
    gens = [r for r in s["stages"] if r["stage"] == "generate"]
    assert len({r["key"] for r in gens}) == 4
    # perfect pairing hashes like a run without the hook: same scenes as the plain generate stage
    plain = run(compose_cfg(base(work) + ["+experiment=pairing_ablation", only, "generate.num_scenes=3",
                                         "stages=[generate]", "variants=null"]))
    assert plain["stages"][0]["key"] == gens[0]["key"] and plain["stages"][0]["hit"]
    cache = work / "cache"
    for (label, e), g in zip(s["evaluate"].items(), gens):
        xi = pd.read_csv(Path(e) / "xi.csv")
        mean = xi[(xi.class_name == "mean") & (xi.condition == "Day-EXTRASUNNY-repeat")
                  & (xi.reference_model == "tiny_segformer")].xi.item()
        row = frame[frame.label == label.split("/")[0]]
        assert row.xi_mean.item() == pytest.approx(mean)
        validation = pd.read_csv(cache / "generate" / g["key"] / "validation.csv")
        assert row.structure_agreement.item() == pytest.approx(validation["structure/Day-EXTRASUNNY-repeat"].mean())
        scene = cache / "generate" / g["key"] / "scenes" / "00000"
        first = cache / "generate" / gens[0]["key"] / "scenes" / "00000"
        # the reference is never perturbed; the adverse view is, from the coarse levels on
        assert np.array_equal(png(scene / "Day-EXTRASUNNY.png"), png(first / "Day-EXTRASUNNY.png"))
        assert (scene / "Day-EXTRASUNNY-repeat_descriptor.json").is_file() == (label != "perfect/tiny_segformer")
    coarse = frame[frame.label == "coarse"].iloc[0]
    assert coarse.camera_jitter_m == 1.5 and coarse.object_resample_prob == 1.0
    # misaligned labels: at the coarse level the repeat's truth differs from the reference's
    gc = cache / "generate" / gens[3]["key"] / "scenes" / "00000"
    assert not np.array_equal(png(gc / "Day-EXTRASUNNY_labels.png"), png(gc / "Day-EXTRASUNNY-repeat_labels.png"))
    assert frame.structure_agreement.iloc[0] > frame.structure_agreement.iloc[-1]
