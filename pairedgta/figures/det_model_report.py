"""A detector placed against a population of detectors (+experiment=model_report task=detection): one page and its
numbers, as segmentation's report (pairedgta/figures/model_report.py) does for segmenters.

The subject is the run's `model` (a zoo detector or one of a researcher's: task=detection model=<source>); the
population is `report.population` or the detection zoo (pairedgta/figures/report_population.py), evaluated on the same
scenes and the reference's boxes; the reference is not ranked. Per pass: `det_model_report.{png,pdf}`,
`det_model_report.md`, `det_model_report.csv` (standing per condition and measure), `det_model_report_tracking.csv`
(detection xi against GT AP within each condition) and `det_model_report_objects.csv` (found share by object height,
the subject beside the population), with panels:

  (a) mean detection xi per adverse condition: the population's box and points, the subject marked, rank, percentile;
  (b) the same for COCO AP against the renderer's boxes;
  (c) per object: the share of the ground-truth objects it finds by object height, beside the population's median
      and range (where each detector stops seeing a pedestrian or a car);
  (d) how well detection xi tracks GT AP across these detectors within each condition, with intervals;
  (e) its worst images: the (scene, condition) pairs where it keeps the smallest share of the reference's boxes.

Statistics as segmentation's report: ranks with ties sharing the better rank, percentiles with ties counted half;
detection xi's percentile intervals resample scenes (every model recomputed on the same draw of groups from its
`detection_group_counts.csv`); AP has no scene interval (COCOeval per resample and model is not run), shown as –."""
from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.errors import ConfigError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, markdown_table, model_display, paper_style, save
from pairedgta.figures.inputs import FigurePass, Passes
from pairedgta.figures.model_report import ci_text, num_text, spread_text, standings, worst_conditions
from pairedgta.figures.model_report_numbers import Report, pct_text, rank_text, row
from pairedgta.figures.report_population import cache_key, evaluations
from pairedgta.metrics.model_report import tracking

log = logging.getLogger("pairedgta.plot")
FIGURE = "det_model_report"
HEIGHT_BINS = (0, 16, 32, 64, 128, 100000)


def _means(e: Any) -> tuple[pd.Series, pd.Series]:
    s = e.summary()
    xi = pd.Series({c: (math.nan if v is None else float(v)) for c, v in (s.get("xi_mean") or {}).items()}, dtype=float)
    ap = pd.Series({c: (math.nan if v is None else float(v)) for c, v in (s.get("gt_ap") or {}).items()}, dtype=float)
    return xi, ap


def _scene_xi(evals: list[Any], conditions: list[str], opts: FigureOptions) -> tuple[np.ndarray | None, int]:
    """M x R x C' mean detection xi on scene resamples (the supported classes of each model and condition as on the
    whole data); None without per-group counts or when the models saw other groups."""
    from pairedgta.metrics.bootstrap import resample_weights

    boot = opts.run.metric.bootstrap
    tables = [e.box_counts() for e in evals]
    if boot.resamples <= 0 or any(t.empty for t in tables):
        return None, (tables[0]["group_id"].nunique() if not tables[0].empty else 0)
    groups = sorted(set(tables[0]["group_id"]))
    if any(sorted(set(t["group_id"])) != groups for t in tables):
        log.warning("det_model_report: the detectors were evaluated on other groups; no scene intervals")
        return None, len(groups)
    w = resample_weights(len(groups), boot.resamples, boot.seed).astype(float)  # R x G
    out = np.full((len(evals), boot.resamples, len(conditions)), np.nan)
    for m, (e, t) in enumerate(zip(evals, tables)):
        xi = e.xi()
        for c, cond in enumerate(conditions):
            ok = xi[(xi["condition"] == cond) & (xi["class_name"] != "mean") & xi["supported"].astype(bool)]
            classes = list(ok["class_name"])
            if not classes:
                continue
            sub = t[(t["condition"] == cond) & t["class_name"].isin(classes)]
            refs = sub.pivot_table(index="group_id", columns="class_name", values="reference_boxes", aggfunc="sum")
            found = sub.pivot_table(index="group_id", columns="class_name", values="found", aggfunc="sum")
            refs, found = refs.reindex(groups).fillna(0).to_numpy(), found.reindex(groups).fillna(0).to_numpy()
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = (w @ found) / (w @ refs)  # R x K; a draw without a class's boxes: NaN, left out of the mean
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                out[m, :, c] = np.nanmean(ratio, axis=1)
    return out, len(groups)


def gather(p: FigurePass, opts: FigureOptions) -> Report:
    run = opts.run
    subject, reference, listed, population, evals = evaluations(p, opts, FIGURE, "detector")
    clean = p.grid.reference
    means = [_means(e) for e in evals]
    present = set().union(*(set(x.index) for x, _ in means))
    conditions = [c for c in p.grid.names if c != clean and c in present]
    xi = np.array([[x.get(c, np.nan) for c in conditions] for x, _ in means], float).reshape(len(evals), -1)
    ap = np.array([[g.get(c, np.nan) for c in conditions] for _, g in means], float).reshape(len(evals), -1)
    ap_clean = np.array([g.get(clean, np.nan) for _, g in means], float)
    scene_xi, n = _scene_xi(evals, conditions, opts)
    scene = None
    if scene_xi is not None:  # AP has no scene resamples: NaN draws give no interval, never a certain one
        nan = np.full_like(scene_xi, np.nan)
        scene = {"xi": scene_xi, "gt": nan, "gt_clean": nan[:, :, 0]}
    boot = run.metric.bootstrap
    missing = [m for m in listed if m not in population]
    n_scenes = int(n or (len(p.dataset) if p.dataset is not None else 0))
    return Report(subject, reference, population, missing, clean, conditions, xi, ap, ap_clean, n_scenes, scene,
                  boot.confidence, boot.resamples, boot.seed)


def objects_table(evals: list[Any], subject: str) -> pd.DataFrame:
    """Per adverse condition and height bin: the share of scored objects each detector finds; the subject's beside
    the population's median, min and max."""
    rows = []
    for e in evals:
        o = e.objects()
        if o.empty:
            continue
        o = o[o["ignore"].fillna("") == ""]
        o = o.assign(bin=pd.cut(o["height"], HEIGHT_BINS, right=False, labels=[
            f"{a}-{b}" if b < 100000 else f">={a}" for a, b in zip(HEIGHT_BINS[:-1], HEIGHT_BINS[1:])]))
        g = o.groupby(["condition", "bin"], observed=True)["found"].agg(["mean", "size"]).reset_index()
        rows += [{"model": e.model, "condition": r.condition, "height_px": str(r.bin), "found_share": float(r.mean),
                  "objects": int(r.size)} for r in g.itertuples()]
    t = pd.DataFrame(rows, columns=["model", "condition", "height_px", "found_share", "objects"])
    if t.empty:
        return t
    mine = t[t["model"] == subject].set_index(["condition", "height_px"])
    pop = t[t["model"] != subject].groupby(["condition", "height_px"])["found_share"].agg(["median", "min", "max"])
    out = mine.join(pop.rename(columns=lambda c: f"population_{c}"), how="left").reset_index()
    return out


def _cases(r: Report, p: FigurePass, subject: Any, k: int) -> list[dict]:
    from pairedgta.detection.boxes import NUM_INSTANCE_CLASSES
    from pairedgta.detection.inputs import image_ids
    from pairedgta.figures.det_qualitative import _from_results
    from pairedgta.metrics.detection_xi import image_counts

    if p.dataset is None or p.pseudo is None or k <= 0:
        return []
    s = subject.summary()
    threshold, iou = float(s["score_threshold"]), p.run.detection.iou
    ids = image_ids(p.dataset)
    groups = {g.group_id: g for g in p.dataset.groups}
    pseudo = p.pseudo.boxes()
    cases = []
    for cond in r.conditions:
        results = subject.detections(cond)
        for gid, ref in pseudo.items():
            if not len(ref.labels) or gid not in groups or cond not in groups[gid].images:
                continue
            boxes, scores, labels = _from_results(results, ids[gid])
            c = image_counts(ref.boxes, ref.labels, boxes, scores, labels, threshold, iou, NUM_INSTANCE_CLASSES)
            cases.append({"condition": cond, "pair_id": gid, "kept": float(c[1].sum() / c[0].sum()),
                          "reference_boxes": int(c[0].sum()), "boxes": boxes, "scores": scores, "labels": labels})
    cases.sort(key=lambda d: (d["kept"], -d["reference_boxes"], d["condition"], d["pair_id"]))
    return cases[:k]


def _objects_panel(ax: Any, table: pd.DataFrame, r: Report) -> None:
    if table.empty:
        ax.axis("off")
        ax.text(0.5, 0.5, "no ground-truth objects", ha="center", va="center", transform=ax.transAxes, fontsize=6)
        return
    bins = list(dict.fromkeys(table["height_px"]))
    x = np.arange(len(bins))
    worst = [w["condition"] for w in r.worst[:2]] or r.conditions[:2]
    from pairedgta.figures.palette import subject_shades  # the subject's colour of every detection figure, and a tint

    for cond, color in zip(worst, subject_shades(r.subject, r.population)):
        t = table[table["condition"] == cond].set_index("height_px").reindex(bins)
        ax.plot(x, t["found_share"], "-D", color=color, ms=3, lw=1, label=f"{model_display(r.subject)}, "
                                                                           f"{condition_display(cond)}")
        ax.fill_between(x, t["population_min"], t["population_max"], color=color, alpha=0.12, lw=0)
        ax.plot(x, t["population_median"], "--", color=color, lw=0.8, label="population median (range shaded)")
    ax.set_xticks(x)
    ax.set_xticklabels(bins)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("object height (px)")
    ax.set_ylabel("share of objects found")
    ax.set_title("(c) objects found by size, its two worst conditions", loc="left")
    ax.legend(fontsize=5, frameon=False, loc="lower right")


def page(r: Report, table: pd.DataFrame, p: FigurePass, out: Path, stem: str, opts: FigureOptions) -> list[Path]:
    from pairedgta.datasets import load_image
    from pairedgta.figures.det_qualitative import _boxes
    from pairedgta.figures.model_report_page import standing_panel, tracking_panel

    n_cases = len(r.cases)
    with paper_style():
        fig = plt.figure(figsize=(TEXT_WIDTH * 1.5, 6.2 + 1.5 * math.ceil(n_cases / 2)))
        grid = fig.add_gridspec(2 + math.ceil(n_cases / 2), 2, height_ratios=[1, 1] + [0.8] * math.ceil(n_cases / 2),
                                hspace=0.55, wspace=0.55)
        standing_panel(fig.add_subplot(grid[0, 0]), r, r.xi, "xi_mean", "(a) mean detection ξ per condition")
        standing_panel(fig.add_subplot(grid[0, 1]), r, r.gt, "gt_miou", "(b) COCO AP per condition")
        _objects_panel(fig.add_subplot(grid[1, 0]), table, r)
        ax = fig.add_subplot(grid[1, 1])
        tracking_panel(ax, r)
        ax.set_xlabel("Spearman(detection ξ, GT AP) across detectors")
        ax.set_title("(d) Spearman(ξ, AP) per condition", loc="left")
        groups = {g.group_id: g for g in p.dataset.groups} if p.dataset is not None else {}
        threshold = _threshold(p, r)
        for i, case in enumerate(r.cases):
            ax = fig.add_subplot(grid[2 + i // 2, i % 2])
            ax.imshow(load_image(groups[case["pair_id"]].images[case["condition"]]))
            keep = case["scores"] >= threshold
            _boxes(ax, case["boxes"][keep], case["labels"][keep], "orange", scores=case["scores"][keep])
            ref = p.pseudo.boxes()[case["pair_id"]]
            _boxes(ax, ref.boxes, ref.labels, "cyan", "--")
            ax.set_title(f"(e) {case['pair_id']} {condition_display(case['condition'])}: keeps {case['kept']:.0%} of "
                         f"{case['reference_boxes']} reference boxes (cyan)", fontsize=5.5, loc="left")
            ax.axis("off")
        fig.suptitle(f"{model_display(r.subject)} against {len(r.population)} detectors on {r.n_scenes} scenes",
                     fontsize=8)
        return save(fig, out, stem, opts.formats, opts.dpi)


def _threshold(p: FigurePass, r: Report) -> float:
    e = next(e for e in p.evaluations if e.model == r.subject)
    return float(e.summary()["score_threshold"])


def markdown(r: Report, table: pd.DataFrame, p: FigurePass, page_name: str) -> str:
    level = f"{r.confidence:.0%}"
    scenes = "none (no per-scene counts, or resamples = 0)" if r.scene is None else (
        f"{level} percentile bootstrap over the {r.n_scenes} scenes ({r.resamples} resamples, every detector "
        "recomputed on the same draw); AP has none (–)")
    missing = f" Listed but not evaluated here: {', '.join(r.missing)}." if r.missing else ""
    text = [f"# Detector report: {r.subject}\n\n{r.subject} placed against {len(r.population)} detector(s) "
            f"({', '.join(r.population)}) on the same {r.n_scenes} scenes of dataset {p.label} and {r.reference}'s "
            f"boxes (the reference, not ranked).{missing} Page: {page_name}.\n\nRank: 1 = best among the subject and "
            f"the members defined in that condition (n); ties share the better rank. Percentile: the share of the "
            f"population the subject beats, ties counted half. Percentile interval: {scenes}.\n"]
    clean = row(r, r.clean, "gt_miou")
    text.append(f"\nClean ({r.clean}) COCO AP: {num_text(clean['subject'])}, rank {rank_text(clean)}, percentile "
                f"{pct_text(clean)}; population {spread_text(clean)} (median [min, max]).\n")
    rows = []
    for cond in r.conditions:
        x, g = row(r, cond, "xi_mean"), row(r, cond, "gt_miou")
        rows.append([cond, num_text(x["subject"]), rank_text(x), pct_text(x), ci_text(x["percentile_ci_low"],
                     x["percentile_ci_high"]), spread_text(x), num_text(g["subject"]), rank_text(g), pct_text(g), spread_text(g)])
    text.append("\n## Per adverse condition\n\n" + markdown_table(
        ["condition", "detection ξ", "ξ rank", "ξ percentile", "ξ percentile CI", "population ξ median [min, max]",
         "AP", "AP rank", "AP percentile", "population AP median [min, max]"], rows))
    rows = [[d["condition"], num_text(d["loss"]), num_text(d["rpc"]), num_text(d["population_median_loss"]), pct_text(d),
             f"{d['n_population']:.0f}"] for d in r.worst]
    what = "COCO AP lost from the clean image" if r.has_gt else "1 − detection ξ (no ground truth)"
    text.append(f"\n## Where it loses most\n\nThe {len(r.worst)} adverse condition(s) with the largest {what}; "
                "percentile: the share of the population that loses more.\n\n" + markdown_table(
                    ["condition", "loss", "rPC (adverse / clean AP)", "population median loss", "percentile",
                     "n population"], rows))
    if not table.empty:
        worst = {d["condition"] for d in r.worst}
        t = table[table["condition"].isin(worst)]
        rows = [[x.condition, x.height_px, f"{x.objects}", num_text(x.found_share), num_text(x.population_median),
                 f"[{num_text(x.population_min)}, {num_text(x.population_max)}]"] for x in t.itertuples()]
        text.append("\n## Objects found by height\n\nThe share of scored ground-truth objects it finds (its confident "
                    "boxes, IoU ≥ 0.5) in its worst conditions, beside the population's.\n\n" + markdown_table(
                        ["condition", "height (px)", "objects", "found", "population median", "population range"],
                        rows))
    if r.cases:
        rows = [[c["condition"], c["pair_id"], str(c["reference_boxes"]), num_text(c["kept"])] for c in r.cases]
        text.append(f"\n## Worst images\n\nIts {len(r.cases)} (scene, condition) pair(s) keeping the smallest share of "
                    "the reference's boxes (panel e).\n\n" + markdown_table(
                        ["condition", "scene", "reference boxes", "kept"], rows))
    rows = []
    for t_ in r.track:
        cond = t_["condition"]
        rows.append([cond if cond != "mean" else f"mean over {t_['n_conditions']} condition(s)",
                     num_text(t_["spearman"], "{:.2f}"), ci_text(t_["scene_ci_low"], t_["scene_ci_high"], "{:.2f}"),
                     ci_text(t_["model_ci_low"], t_["model_ci_high"], "{:.2f}"), str(t_["n_models"])])
    text.append(f"\n## How well detection ξ tracks AP on these scenes\n\nSpearman of mean detection ξ against COCO AP "
                f"across the {len(r.models)} ranked detectors within each condition (pooled over conditions it would "
                f"mostly order the conditions by severity); intervals at {level} over models (drawn with "
                f"replacement); – where undefined.\n\n" + markdown_table(
                    ["condition", "Spearman(ξ, AP)", "scene CI", "model CI", "n models"], rows))
    return "".join(text)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if not p.evaluations:
            continue
        r = gather(p, opts)
        standings(r)
        r.track = tracking(r.xi, r.gt, r.conditions, r.scene["xi"] if r.scene else None,
                           r.scene["gt"] if r.scene else None, r.resamples, r.confidence, r.seed, r.n_scenes)
        worst_conditions(r, opts.run.report.worst_conditions)
        evals = {e.model: e for e in p.evaluations}
        r.cases = _cases(r, p, evals[r.subject], opts.run.report.worst_cases)
        table = objects_table([evals[m] for m in r.models], r.subject)
        stem = opts.stem(FIGURE, p.label)
        drawn = page(r, table, p, out, stem, opts)
        (out / f"{stem}.md").write_text(markdown(r, table, p, ", ".join(q.name for q in drawn)), encoding="utf-8")
        pd.DataFrame(r.rows).replace({"measure": {"gt_miou": "gt_ap", "gt_miou_drop": "gt_ap_drop"}}).assign(
            model=r.subject).to_csv(out / f"{stem}.csv", index=False)
        pd.DataFrame(r.track).assign(model=r.subject).to_csv(out / f"{stem}_tracking.csv", index=False)
        table.to_csv(out / f"{stem}_objects.csv", index=False)
        files += [*drawn, out / f"{stem}.md", out / f"{stem}.csv", out / f"{stem}_tracking.csv",
                  out / f"{stem}_objects.csv"]
        opts.point(drawn[0], f"detector report of {r.subject} ({stem}.md beside it)")
        prefix = "report/" if not opts.multi else f"report/{p.label}/"
        for d in r.rows:
            measure = {"gt_miou": "det_ap", "gt_miou_drop": "det_ap_drop", "xi_mean": "det_xi_mean"}[d["measure"]]
            for stat in ("rank", "percentile"):
                if math.isfinite(d[stat]):
                    metrics[f"{prefix}{measure}/{stat}/{d['condition']}"] = float(d[stat])
        metrics[f"{prefix}population_size"] = float(len(r.population))
    if not files:
        raise ConfigError(f"plot.figures: {FIGURE} found no evaluation to draw; run it with stages=[evaluate,plot]")
    return files, metrics


__all__ = ["FIGURE", "cache_key", "draw", "gather", "markdown", "objects_table"]  # cache_key: the FigureSpec's key
