"""Plot stage: the paper's figures and tables from the cached stage outputs of one or more passes (a pass
= one dataset variant: the generated dataset, ACDC, a pairing level ...). `plot.figures` picks the
families (modules of pairedgta.figures):

    xi_table      Table 1 as CSV/Markdown/LaTeX (best per column bold) + the xi heatmap     needs evaluate
    ranking       the ranking figure per dataset x model x class + the rho_valid table      needs evaluate
    qualitative   worst/best groups per condition: images, predictions, confidence, errors needs evaluate
    ablation      mean xi / rho_valid / pair structure per pairing level                    needs evaluate
    distribution  pseudo-label pixel mass per class with an example                         needs pseudolabel
    cost          per-scene time boxplots and the phase split (+ the paper's CSV)           needs generate

Every output is written into the stage's cache directory; `metrics.json` holds the numbers the run logs
to MLflow (so a cache hit logs them too)."""
from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pairedgta.conditions import ConditionGrid
from pairedgta.datasets import PairedDataset
from pairedgta.errors import ConfigError
from pairedgta.figures.common import slug
from pairedgta.cache import require_intact
from pairedgta.jsonio import write_json
from pairedgta.stages.common import Context, StageResult, run_cached

log = logging.getLogger("pairedgta.plot")
VERSION = "2"
NEEDS = {
    "xi_table": "evaluate", "ranking": "evaluate", "qualitative": "evaluate", "ablation": "evaluate",
    "distribution": "pseudolabel", "cost": "generate", "contact_sheet": "generate",
}
DEFAULT_FIGURES = ("xi_table", "ranking", "qualitative")


@dataclass
class PassResult:
    """One dataset variant of the run and its stage results."""

    label: str
    cfg: dict[str, Any]
    grid: ConditionGrid
    dataset: PairedDataset | None = None
    dataset_key: str | None = None
    generate: StageResult | None = None
    pseudo: StageResult | None = None
    evaluations: list[StageResult] = field(default_factory=list)


def figures_of(cfg: dict[str, Any]) -> list[str]:
    figures = list((cfg.get("plot") or {}).get("figures") or DEFAULT_FIGURES)
    unknown = [f for f in figures if f not in NEEDS]
    if unknown:
        raise ConfigError(f"plot.figures: unknown {unknown}; known: {', '.join(NEEDS)}")
    return figures


def needed_stages(cfg: dict[str, Any]) -> set[str]:
    """Which upstream stages the requested figures read (cost from a given CSV needs none)."""
    needs = set()
    for f in figures_of(cfg):
        if f == "cost" and (cfg.get("cost") or {}).get("csv"):
            continue
        needs.add(NEEDS[f])
    return needs


def _read(evaluations: list[StageResult], name: str) -> pd.DataFrame:
    frames = [pd.read_csv(e.path / name, dtype={"pair_id": str}) for e in evaluations if (e.path / name).is_file()]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def cost_sources(ctx: Context, passes: list[PassResult]) -> list[tuple[str, str, Path]]:
    """(metric key, label, CSV) of every timing source: the paper's CSV (cost.paper), then cost.csv or
    this run's generate timings."""
    from pairedgta.data import PAPER_GENERATION_TIMES

    ccfg = ctx.cfg.get("cost") or {}
    sources: list[tuple[str, str, Path]] = []
    if ccfg.get("paper", True):
        sources.append(("paper", str(ccfg.get("paper_label") or "paper (GTA V, RTX 2080)"), PAPER_GENERATION_TIMES))
    if ccfg.get("csv"):
        path = Path(str(ccfg["csv"]))
        sources.append((slug(str(ccfg.get("label") or path.stem)), str(ccfg.get("label") or path.stem), path))
    else:
        for p in passes:
            if p.generate is not None:
                backend = (p.cfg.get("renderer") or {}).get("backend", "renderer")
                label = str(ccfg.get("label") or f"this run ({backend})")
                key = "run" if len(passes) == 1 else f"run_{slug(p.label)}"
                sources.append((key, label if len(passes) == 1 else f"{label} {p.label}", p.generate.path / "timings.csv"))
    return sources


def make_plots(ctx: Context, passes: list[PassResult], out: Path) -> dict[str, Any]:
    pcfg = ctx.cfg["plot"]
    formats, dpi = list(pcfg.get("formats", ["png"])), int(pcfg.get("dpi", 150))
    figures = figures_of(ctx.cfg)
    files: list[Path] = []
    metrics: dict[str, float] = {}
    multi = len(passes) > 1

    def suffix(p: PassResult) -> str:
        return f"_{slug(p.label)}" if multi else ""

    evaluated = [p for p in passes if p.evaluations]
    if "xi_table" in figures:
        from pairedgta.figures import xi as xi_fig

        for p in evaluated:
            xi = _read(p.evaluations, "xi.csv")
            pl = xi[xi["reference_model"] != "ground_truth"]
            files += xi_fig.heatmap_figure(pl, p.grid.reference, out, formats, dpi, stem=f"xi_table{suffix(p)}")
            files += xi_fig.write_tables(pl, p.grid.reference, out, stem=f"table1_xi{suffix(p)}")
            pl.to_csv(out / f"xi_all_models{suffix(p)}.csv", index=False)
            files.append(out / f"xi_all_models{suffix(p)}.csv")
            for r in pl[pl["class_name"] == "mean"].itertuples():
                metrics[f"table/{p.label}/xi_mean/{r.condition}/{r.model}"] = r.xi

    ranking = pcfg.get("ranking") or {}
    classes = list(ranking.get("classes") or ["person", "car"])
    if "ranking" in figures and evaluated:
        from pairedgta.figures.ranking import RankingInput, pick_condition, ranking_figure, rho_table

        inputs = []
        for p in evaluated:
            counts = _read(p.evaluations, "frame_counts.csv")
            rho = _read(p.evaluations, "rho_valid.csv")
            wanted = ((p.cfg.get("plot") or {}).get("ranking") or {}).get("condition")
            cond = pick_condition(list(dict.fromkeys(counts["condition"])) if not counts.empty else [], wanted, p.grid.reference)
            if cond is not None:
                inputs.append(RankingInput(p.label, cond, counts, rho))
        selections = tuple((ctx.cfg.get("metric") or {}).get("rho", {}).get("selections") or ("top_m", "nonzero"))
        files += ranking_figure(inputs, classes, int(ranking.get("window", 5)), out, formats, dpi, selections=selections)
        files += rho_table(inputs, classes, out)
        for inp in inputs:
            r = inp.rho[(inp.rho["condition"] == inp.condition) & inp.rho["class_name"].isin(classes)]
            for row in r.itertuples():
                metrics[f"rho_valid/{inp.label}/{row.model}/{row.selection}/{row.class_name}"] = row.rho

    if "qualitative" in figures:
        from pairedgta.figures.qualitative import qualitative_grid

        n = int(pcfg.get("qualitative_groups", 2))
        wanted = pcfg.get("qualitative_conditions")
        tables = []
        for p in evaluated:
            if p.dataset is None or p.pseudo is None or n < 1:
                continue
            clean = _clean_condition(p)
            conditions = [c for c in p.grid.names if c != clean and (not wanted or c in wanted)]
            for e in p.evaluations:
                manifest = json.loads((e.path / "manifest.json").read_text())
                model_cfg = {**manifest["config"]["model"], "device": ctx.cfg.get("device", "cpu")}
                agreement = pd.read_csv(e.path / "pixel_agreement.csv", dtype={"pair_id": str})
                paths, table = qualitative_grid(
                    p.dataset, p.pseudo.path, agreement, model_cfg, conditions, n, clean, out,
                    f"qualitative{suffix(p)}_{slug(model_cfg['name'])}", formats, dpi,
                    title=f"{p.label} \u00b7 {model_cfg['name']}" if multi else "",
                )
                files += paths
                if not table.empty:
                    table.insert(0, "dataset_label", p.label)
                    tables.append(table)
        if tables:
            pd.concat(tables, ignore_index=True).to_csv(out / "qualitative.csv", index=False)
            files.append(out / "qualitative.csv")

    if "ablation" in figures and evaluated:
        from pairedgta.figures.ablation import Level, ablation_figure, ablation_frame, ablation_table
        from pairedgta.stages.generate import pairing_config

        selections = list((ctx.cfg.get("metric") or {}).get("rho", {}).get("selections") or ["top_m"])
        selection = str((pcfg.get("ablation") or {}).get("selection") or selections[0])
        levels = []
        for p in evaluated:
            validation = None
            if p.generate is not None and (p.generate.path / "validation.csv").is_file():
                validation = pd.read_csv(p.generate.path / "validation.csv", dtype={"scene_id": str})
            levels.append(Level(p.label, pairing_config(p.cfg.get("generate") or {}), _read(p.evaluations, "xi.csv"),
                                _read(p.evaluations, "rho_valid.csv"), validation))
        frame = ablation_frame(levels, evaluated[0].grid.reference, classes, selection)
        files += ablation_figure(frame, classes, selection, out, formats, dpi)
        files += ablation_table(frame, classes, selection, out)
        for r in frame.to_dict("records"):
            base = f"ablation/{r['label']}/{r['model']}/{r['condition']}"
            metrics[f"{base}/xi_mean"] = r["xi_mean"]
            for c in classes:
                metrics[f"{base}/rho_valid/{selection}/{c}"] = r[f"rho_{selection}_{c}"]
            metrics[f"{base}/structure_agreement"] = r["structure_agreement"]

    if "distribution" in figures:
        from pairedgta.figures.distribution import distribution_figure, distribution_table

        for p in passes:
            if p.pseudo is None or p.dataset is None:
                continue
            paths, _example = distribution_figure(
                p.dataset, p.pseudo.path, str(p.cfg["reference_model"]), float(p.cfg["pseudolabel"]["tau"]), out,
                formats, dpi, example=pcfg.get("distribution_example"), stem=f"pseudo_label_distribution{suffix(p)}",
            )
            files += paths
            files += distribution_table(p.pseudo.path, out, stem=f"pixel_mass{suffix(p)}")
            hist = pd.read_csv(p.pseudo.path / "histogram.csv")
            for r in hist.itertuples():
                metrics[f"pseudo_label/{p.label}/share_of_valid/{r.class_name}"] = r.share_of_valid
            metrics[f"pseudo_label/{p.label}/void_share"] = 1 - float(hist["share_of_all"].sum())

    if "contact_sheet" in figures:
        from pairedgta.figures.contact_sheet import contact_sheet

        for p in passes:
            if p.dataset is not None and p.generate is not None:
                files += contact_sheet(p.dataset, p.grid.names, out, ["png"], dpi, stem=f"contact_sheet{suffix(p)}")

    if "cost" in figures:
        from pairedgta.figures.cost import cost_figure, cost_table, load_timings, summary

        listed = cost_sources(ctx, passes)
        sources = [load_timings(path, label) for _, label, path in listed]
        if sources:
            files += cost_figure(sources, out, formats, dpi)
            files += cost_table(sources, out)
            for (key, _, _), t in zip(listed, sources):
                for k, v in summary(t).items():
                    metrics[f"cost/{key}/{k}"] = v
                for note in t.notes:
                    log.info("cost, %s: %s", t.label, note)

    clean_metrics = {k: float(v) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
    write_json(out / "metrics.json", clean_metrics, sort_keys=True)
    return {"figures": [p.name for p in files], "metrics": clean_metrics}


def _clean_condition(p: PassResult) -> str:
    clean = ((p.cfg.get("metric") or {}).get("rho") or {}).get("clean_condition")
    return clean if clean in p.grid.names else p.grid.reference


def run(ctx: Context, passes: list[PassResult]) -> StageResult:
    figures = figures_of(ctx.cfg)
    for e in (e for p in passes for e in p.evaluations):
        require_intact(e.path, "evaluate")  # a collected evaluation missing a file must not drop out silently
    config: dict[str, Any] = {"plot": ctx.cfg["plot"], "reference": [p.grid.reference for p in passes]}
    inputs: dict[str, str] = {}
    for i, p in enumerate(passes):
        tag = f"{i}:{p.label}"
        if p.pseudo is not None:
            inputs[f"{tag}/pseudolabel"] = p.pseudo.key
        for j, e in enumerate(sorted(p.evaluations, key=lambda e: e.key)):
            inputs[f"{tag}/evaluate/{j}"] = e.key
        if p.generate is not None and ("cost" in figures or "ablation" in figures):
            inputs[f"{tag}/generate"] = p.generate.key
        if "ablation" in figures:
            from pairedgta.stages.generate import pairing_config

            config.setdefault("pairing", {})[tag] = pairing_config(p.cfg.get("generate") or {})
    if "cost" in figures:
        config["cost"] = ctx.cfg.get("cost") or {}
        for key, _, path in cost_sources(ctx, passes):
            if path.is_file():
                inputs[f"cost/{key}"] = _file_hash(path)
    if "distribution" in figures:
        config["reference_model"] = [p.cfg.get("reference_model") for p in passes]
    return run_cached(ctx, "plot", VERSION, config, inputs, lambda out: make_plots(ctx, passes, out))
