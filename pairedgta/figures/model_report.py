"""A model placed against a population (+experiment=model_report): one page and its numbers as tables.

The subject is the run's `model`; the population is `report.population` or the offline zoo
(pairedgta/figures/report_population.py), evaluated on the same scenes and pseudo-labels; the reference model is not
ranked.
Per pass it writes `model_report.{png,pdf}` (plot.formats), `model_report.md`, `model_report.csv` (the subject's
standing per condition and measure) and `model_report_tracking.csv` (xi against GT within each condition), with
panels:

  (a) mean xi per adverse condition: the population's box and points, the subject marked, its rank and percentile;
  (b) the same for GT mIoU;
  (c) where it loses most: the subject's GT mIoU lost from the clean image per condition beside the population's
      losses, the `report.worst_conditions` largest marked, with the share of the population that loses more;
  (d) its worst images: the `report.worst_cases` (group, condition) pairs with the lowest pixel agreement with the
      pseudo-labels, as evaluate predicted them (its predictions.npz): image | pseudo-label | prediction | disagreement;
  (e) how well xi tracks ground truth on these scenes: Spearman of mean xi against GT mIoU across the population and
      the subject within each condition, with intervals over scenes and over models, and the subject's xi rank
      against its GT rank.

The markdown also gives the subject's rank by xi_F (the F of xi and its precision, evaluate's xi_precision.csv)
beside its rank by xi: xi is a recall, which a model that paints one class everywhere keeps for that class.

Statistics (pairedgta/metrics/model_report.py): ranks with ties sharing the better rank, percentiles with ties
counted half, percentile intervals over the scenes (every model recomputed on the same draw of groups from evaluate's
per-group counts); no interval where the resamples do not vary; n said everywhere."""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import load_group_images
from pairedgta.errors import ConfigError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import markdown_table
from pairedgta.figures.inputs import Evaluation, FigurePass, Passes
from pairedgta.figures.model_report_numbers import Report, pct_text, rank_text, row
from pairedgta.figures.qualitative import AGREEMENT_TOL, clean_condition
from pairedgta.figures.report_population import cache_key, evaluations
from pairedgta.metrics.model_report import standing, standing_interval, tracking

log = logging.getLogger("pairedgta.plot")
GT_SOURCE = "ground_truth"  # the xi rows scored against the true labels, not the pseudo-labels
__all__ = ["Report", "cache_key", "ci_text", "compute", "draw", "markdown", "num_text", "spread_text", "standings",
           "worst_conditions"]  # cache_key: the FigureSpec's key, read from here too


def _means(e: Evaluation) -> tuple[pd.Series, pd.Series]:
    """An evaluation's mean xi (against the pseudo-labels) and GT mIoU per condition."""
    xi = e.xi()
    xi = xi[(xi["reference_model"] != GT_SOURCE) & (xi["class_name"] == "mean")]
    gt = e.gt_iou()
    gt = gt[gt["class_name"] == "mean"] if not gt.empty else gt
    return (xi.set_index("condition")["xi"].astype(float),
            gt.set_index("condition")["iou"].astype(float) if not gt.empty else pd.Series(dtype=float))


def _f_means(e: Evaluation) -> pd.Series:
    """An evaluation's mean F of xi and its precision (against the pseudo-labels) per condition; empty for an entry
    written before xi_precision.csv."""
    from pairedgta.evaluation.xi_precision import XI_PRECISION

    path = Path(e.path) / XI_PRECISION
    if not path.is_file():
        return pd.Series(dtype=float)
    t = pd.read_csv(path)
    t = t[(t["reference_model"] != GT_SOURCE) & (t["class_name"] == "mean")]
    return t.set_index("condition")["xi_f"].astype(float)


def _scene_values(evals: list[Evaluation], clean: str, conditions: list[str], opts: FigureOptions,
                  ) -> tuple[dict[str, np.ndarray] | None, int | None]:
    """Every model's mean xi and GT mIoU recomputed on the same scene resamples (evaluate's per-group counts); None
    where an entry has no counts or the models were evaluated on other groups."""
    from pairedgta.metrics import mean_mask
    from pairedgta.metrics.bootstrap import resample_weights
    from pairedgta.metrics.conventions import convention_from_config
    from pairedgta.metrics.validity import GroupCounts, cell_measures, precision_measures
    from pairedgta.schema import as_dict

    boot = opts.run.metric.bootstrap
    counts = [e.group_counts() for e in evals]
    if boot.resamples <= 0 or not all(c and "cm" in c for c in counts):
        return None, (len(counts[0]["group_id"]) if counts and counts[0] else None)
    groups = [GroupCounts.from_arrays(e.model, c) for e, c in zip(evals, counts)]
    first = groups[0]
    if any(g.group_ids != first.group_ids or g.conditions != first.conditions for g in groups) or \
            clean not in first.conditions:
        log.warning("model_report: the models were evaluated on other groups or conditions; no scene intervals")
        return None, None
    conv = convention_from_config(as_dict(opts.run.metric))
    include = mean_mask(NUM_CLASSES, CLASS_NAMES, conv.mean_exclude)
    n = groups[0].pl_retained.shape[0]
    w = resample_weights(n, boot.resamples, boot.seed).astype(float)
    idx = [groups[0].conditions.index(c) if c in groups[0].conditions else None for c in conditions]
    xi, gt, clean_gt, xi_f = [], [], [], []
    for g in groups:
        m = cell_measures(g, w, clean, include, conv.absent, conv.min_images, conv.min_pixels)
        f = precision_measures(g, w, include, conv.absent, conv.min_images, conv.min_pixels)["xi_f_mean"]
        nan = np.full(len(w), np.nan)
        xi.append(np.stack([m["xi_mean"][:, i] if i is not None else nan for i in idx], axis=1))
        gt.append(np.stack([m["gt_miou"][:, i] if i is not None else nan for i in idx], axis=1))
        xi_f.append(np.stack([f[:, i] if i is not None else nan for i in idx], axis=1))
        clean_gt.append(m["gt_miou"][:, groups[0].conditions.index(clean)])
    return {"xi": np.stack(xi), "gt": np.stack(gt), "gt_clean": np.stack(clean_gt), "xi_f": np.stack(xi_f)}, n


def gather(p: FigurePass, opts: FigureOptions) -> Report:
    """The subject's and its population's values on pass `p`."""
    run = opts.run
    subject, reference, listed, population, evals = evaluations(p, opts, "model_report", "model")
    clean = clean_condition(p)
    means = [_means(e) for e in evals]
    present = set().union(*(set(x.index) for x, _ in means))
    conditions = [c for c in p.grid.names if c != clean and c in present]
    xi = np.array([[x.get(c, np.nan) for c in conditions] for x, _ in means], float).reshape(len(evals), -1)
    gt = np.array([[g.get(c, np.nan) for c in conditions] for _, g in means], float).reshape(len(evals), -1)
    gt_clean = np.array([g.get(clean, np.nan) for _, g in means], float)
    f_means = [_f_means(e) for e in evals]
    xi_f = np.array([[f.get(c, np.nan) for c in conditions] for f in f_means], float).reshape(len(evals), -1)
    boot = run.metric.bootstrap
    scene, n_scenes = _scene_values(evals, clean, conditions, opts)
    if n_scenes is None:
        n_scenes = len(p.dataset) if p.dataset is not None else 0
    missing = [m for m in listed if m not in population]
    return Report(subject, reference, population, missing, clean, conditions, xi, gt, gt_clean, int(n_scenes), scene,
                  boot.confidence, boot.resamples, boot.seed, xi_f)


def _standing(r: Report, condition: str, measure: str, values: np.ndarray, scene: np.ndarray | None,
              higher: bool = True) -> dict:
    """values: M (the subject first); scene: M x R or None -> the subject's standing, its percentile interval over
    scenes and the population's spread."""
    s = standing(values[0], values[1:], higher)
    lo = hi = math.nan
    if scene is not None and math.isfinite(s["percentile"]):
        lo, hi = standing_interval(scene[0], scene[1:].T, r.confidence, higher)
    pop = values[1:][np.isfinite(values[1:])]
    spread = (float(np.median(pop)), float(pop.min()), float(pop.max())) if pop.size else (math.nan,) * 3
    return {"condition": condition, "measure": measure, "subject": float(values[0]), **s, "percentile_ci_low": lo,
            "percentile_ci_high": hi, **dict(zip(("population_median", "population_min", "population_max"), spread))}


def standings(r: Report) -> None:
    """The subject's standing per adverse condition and measure, and the clean image's GT mIoU (where losses start)."""
    values = {"xi_mean": r.xi, "gt_miou": r.gt, "gt_miou_drop": r.gt_clean[:, None] - r.gt}
    scene = None if r.scene is None else {"xi_mean": r.scene["xi"], "gt_miou": r.scene["gt"],
                                          "gt_miou_drop": r.scene["gt_clean"][:, :, None] - r.scene["gt"]}
    if r.xi_f is not None and np.isfinite(r.xi_f).any():  # the F of xi and its precision: its rank beside xi's
        values["xi_f"] = r.xi_f
        if scene is not None:
            scene["xi_f"] = r.scene["xi_f"]
    r.rows = [_standing(r, cond, measure, v[:, c], None if scene is None else scene[measure][:, :, c],
                        higher=measure != "gt_miou_drop")
              for measure, v in values.items() for c, cond in enumerate(r.conditions)]
    r.rows.append(_standing(r, r.clean, "gt_miou", r.gt_clean, None if r.scene is None else r.scene["gt_clean"]))


def worst_conditions(r: Report, k: int) -> None:
    """The k conditions where the subject loses the most GT mIoU from the clean image (1 − ξ without labels)."""
    out = []
    for c, cond in enumerate(r.conditions):
        d = row(r, cond, "gt_miou_drop" if r.has_gt else "xi_mean")  # its percentile: the share losing more either way
        loss, med = d["subject"], d["population_median"]
        if not r.has_gt:
            loss, med = 1 - loss, 1 - med
        rpc = r.gt[0, c] / r.gt_clean[0] if r.gt_clean[0] > 0 else math.nan
        out.append({"condition": cond, "loss": loss, "rpc": rpc, "population_median_loss": med,
                    **{k: d[k] for k in ("percentile", "percentile_ci_low", "percentile_ci_high", "n_population")}})
    out.sort(key=lambda d: (-d["loss"] if math.isfinite(d["loss"]) else math.inf, r.conditions.index(d["condition"])))
    r.worst = out[:k]


def _cases(r: Report, p: FigurePass, subject: Evaluation, k: int, device: str) -> list[dict]:
    """The subject's k (group, condition) images with the lowest pixel agreement, as evaluate predicted them."""
    from pairedgta.evaluation.entry import PREDICTIONS
    from pairedgta.figures.qualitative import Predictions

    a = subject.agreement()
    a = a[(a["pair_id"] != "ALL") & a["condition"].isin(r.conditions) & a["agreement_reference"].notna()]
    a = a.sort_values(["agreement_reference", "condition", "pair_id"], kind="stable").head(k)
    if a.empty or p.dataset is None or p.pseudo is None:
        return []
    predictions = Predictions(subject.path / PREDICTIONS, subject.model_config(), device, confidence=False)
    groups = {g.group_id: g for g in p.dataset.groups}
    cases = []
    for row_ in a.itertuples():
        group = groups.get(str(row_.pair_id))
        if group is None or row_.condition not in group.images:
            continue
        image = load_group_images(group, [row_.condition])[row_.condition]
        pseudo = p.pseudo.labels.load(group.group_id).astype(np.int64)
        pred = predictions(group, row_.condition, image)[0]
        valid = pseudo != IGNORE_INDEX
        again = float(((pred == pseudo) & valid).sum() / valid.sum()) if valid.any() else math.nan
        if not math.isclose(again, float(row_.agreement_reference), abs_tol=AGREEMENT_TOL):
            log.warning("model_report %s/%s: recomputed agreement %.4f differs from evaluate's %.4f", row_.condition,
                        group.group_id, again, float(row_.agreement_reference))
        cases.append({"condition": row_.condition, "pair_id": group.group_id,
                      "agreement": float(row_.agreement_reference),
                      "agreement_recomputed": again, "image": image, "pseudo": pseudo, "prediction": pred})
    return cases


def compute(p: FigurePass, opts: FigureOptions) -> Report:
    """Every number of the report of pass `p` (the cases' images too)."""
    r = gather(p, opts)
    standings(r)
    r.track = tracking(r.xi, r.gt, r.conditions, r.scene["xi"] if r.scene else None, r.scene["gt"] if r.scene else None,
                       r.resamples, r.confidence, r.seed, r.n_scenes)
    worst_conditions(r, opts.run.report.worst_conditions)
    subject = next(e for e in p.evaluations if e.model == r.subject)
    if opts.run.report.worst_cases > 0:
        r.cases = _cases(r, p, subject, opts.run.report.worst_cases, opts.run.device)
    return r


# -- text ---------------------------------------------------------------------------------------------------------
def num_text(v: float, fmt: str = "{:.3f}") -> str:
    return "–" if v is None or not math.isfinite(v) else fmt.format(v)


def ci_text(lo: float, hi: float, fmt: str = "{:.1f}") -> str:
    return "–" if not (math.isfinite(lo) and math.isfinite(hi)) else f"[{fmt.format(lo)}, {fmt.format(hi)}]"


def spread_text(d: dict) -> str:
    return f"{num_text(d['population_median'])} [{num_text(d['population_min'])}, {num_text(d['population_max'])}]"


def markdown(r: Report, p: FigurePass, page: str) -> str:
    level = f"{r.confidence:.0%}"
    scenes = "none (no per-scene counts, or resamples = 0)"
    if r.scene is not None:
        scenes = (f"{level} percentile bootstrap over the {r.n_scenes} scenes ({r.resamples} resamples, every model "
                  f"recomputed on the same draw)")
    missing = (f" Listed but not evaluated here: {', '.join(r.missing)}." if r.missing else "")
    text = [f"# Model report: {r.subject}\n\n"
            f"{r.subject} placed against {len(r.population)} model(s) ({', '.join(r.population)}) on the same "
            f"{r.n_scenes} scenes of dataset {p.label} and {r.reference}'s pseudo-labels (the reference model, not "
            f"ranked).{missing} Page: {page}.\n\n"
            f"Rank: 1 = best among the subject and the members defined in that condition (n); tied members share the "
            f"better rank. Percentile: the share of the population the subject beats, ties counted half (100 = above "
            f"every member). Percentile interval: {scenes}; – where the resamples do not vary or fewer than half "
            f"define it (no interval is no certainty).\n"]
    clean = row(r, r.clean, "gt_miou")
    text.append(f"\nClean ({r.clean}) GT mIoU: {num_text(clean['subject'])}, rank {rank_text(clean)}, percentile "
                f"{pct_text(clean)} {ci_text(clean['percentile_ci_low'], clean['percentile_ci_high'])}; population "
                f"{spread_text(clean)} (median [min, max]).\n")
    rows = []
    has_f = any(d["measure"] == "xi_f" for d in r.rows)
    for cond in r.conditions:
        x, g = row(r, cond, "xi_mean"), row(r, cond, "gt_miou")
        f = [num_text(row(r, cond, "xi_f")["subject"]), rank_text(row(r, cond, "xi_f"))] if has_f else []
        rows.append([cond, *(cell for d in (x,) for cell in (
            num_text(d["subject"]), rank_text(d), pct_text(d), ci_text(d["percentile_ci_low"], d["percentile_ci_high"]),
            spread_text(d))), *f, *(cell for d in (g,) for cell in (
            num_text(d["subject"]), rank_text(d), pct_text(d), ci_text(d["percentile_ci_low"], d["percentile_ci_high"]),
            spread_text(d)))])
    f_note = ("ξ_F: the harmonic mean of ξ and its precision per class (of the pixels the model predicts as a class "
              "on the pseudo-label's valid pixels, the share whose pseudo-label is that class), class-wise mean over "
              "ξ's classes (evaluate's xi_precision.csv): ξ is a recall, which a model painting one class everywhere "
              "keeps for that class; ξ_F sees it.\n\n") if has_f else ""
    text.append("\n## Per adverse condition\n\n" + f_note + markdown_table(
        ["condition", "ξ", "ξ rank", "ξ percentile", "ξ percentile CI", "population ξ median [min, max]",
         *(["ξ_F", "ξ_F rank"] if has_f else []),
         "GT mIoU", "GT mIoU rank", "GT mIoU percentile", "GT mIoU percentile CI",
         "population GT mIoU median [min, max]"], rows))
    what = ("GT mIoU lost from the clean image" if r.has_gt else "1 − ξ (no ground truth)")
    rows = [[d["condition"], num_text(d["loss"]), num_text(d["rpc"]), num_text(d["population_median_loss"]), pct_text(d),
             ci_text(d["percentile_ci_low"], d["percentile_ci_high"]), f"{d['n_population']:.0f}"] for d in r.worst]
    text.append(f"\n## Where it loses most\n\nThe {len(r.worst)} adverse condition(s) with the largest {what}; "
                f"percentile: the share of the population that loses more (ties half).\n\n" + markdown_table(
                    ["condition", "loss", "rPC (adverse / clean GT mIoU)", "population median loss", "percentile",
                     "percentile CI", "n population"], rows))
    if r.cases:
        rows = [[c["condition"], c["pair_id"], num_text(c["agreement"])] for c in r.cases]
        text.append(f"\n## Worst images\n\nIts {len(r.cases)} (scene, condition) pair(s) with the lowest pixel "
                    f"agreement with the pseudo-labels (panel d).\n\n"
                    + markdown_table(["condition", "scene", "pixel agreement"], rows))
    xi_rank = {d["condition"]: d for d in r.rows if d["measure"] == "xi_mean"}
    gt_rank = {d["condition"]: d for d in r.rows if d["measure"] == "gt_miou"}
    f_rank = {d["condition"]: d for d in r.rows if d["measure"] == "xi_f"}
    ranked = (xi_rank, f_rank, gt_rank) if has_f else (xi_rank, gt_rank)
    rows = []
    for t in r.track:
        cond = t["condition"]
        rows.append([cond if cond != "mean" else f"mean over {t['n_conditions']} condition(s)",
                     num_text(t["spearman"], "{:.2f}"), ci_text(t["scene_ci_low"], t["scene_ci_high"], "{:.2f}"),
                     ci_text(t["model_ci_low"], t["model_ci_high"], "{:.2f}"), str(t["n_models"]),
                     *(rank_text(ranks[cond]) if cond in ranks else "–" for ranks in ranked)])
    text.append(f"\n## How well ξ tracks ground truth on these scenes\n\nSpearman of mean ξ against GT mIoU across "
                f"the "
                f"{len(r.models)} ranked models (the population and {r.subject}) within each condition: pooled over "
                f"conditions it would mostly order the conditions by severity. Intervals at {level}: over scenes (as "
                f"above) and over models (the models drawn with replacement, {r.resamples} draws, fewer than 3 "
                f"distinct undefined); – where undefined (fewer than 3 models, a constant column) or the resamples do "
                f"not vary. "
                f"n: the models with both values in that condition. The last columns: where ξ"
                f"{', ξ_F (ξ with its precision)' if has_f else ''} and ground truth place {r.subject}.\n\n"
                + markdown_table(["condition", "Spearman(ξ, GT mIoU)", "scene CI", "model CI", "n models",
                                  f"{r.subject}'s ξ rank", *([f"{r.subject}'s ξ_F rank"] if has_f else []),
                                  f"{r.subject}'s GT rank"], rows))
    return "".join(text)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """One report per pass with evaluations (one for the model_report experiment)."""
    from pairedgta.figures.model_report_page import page

    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if not p.evaluations:
            continue
        r = compute(p, opts)
        stem = opts.stem("model_report", p.label)
        drawn = page(r, out, stem, opts)  # matplotlib: pairedgta/figures/model_report_page.py
        (out / f"{stem}.md").write_text(markdown(r, p, ", ".join(q.name for q in drawn)), encoding="utf-8")
        pd.DataFrame(r.rows).assign(model=r.subject).to_csv(out / f"{stem}.csv", index=False)
        pd.DataFrame(r.track).assign(model=r.subject).to_csv(out / f"{stem}_tracking.csv", index=False)
        files += [*drawn, out / f"{stem}.md", out / f"{stem}.csv", out / f"{stem}_tracking.csv"]
        opts.point(drawn[0], f"model report of {r.subject} ({stem}.md beside it)")
        prefix = "report/" if not opts.multi else f"report/{p.label}/"
        for d in r.rows:
            for stat in ("rank", "percentile"):
                if math.isfinite(d[stat]):
                    metrics[f"{prefix}{d['measure']}/{stat}/{d['condition']}"] = float(d[stat])
        for t in r.track:
            if math.isfinite(t["spearman"]):
                metrics[f"{prefix}spearman_xi_gt/{t['condition']}"] = float(t["spearman"])
        metrics[f"{prefix}population_size"] = float(len(r.population))
    if not files:
        raise ConfigError("plot.figures: model_report found no evaluation to draw; run it with stages=[evaluate,plot]")
    return files, metrics
