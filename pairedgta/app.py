"""The stage graph: generate -> pseudolabel -> evaluate -> plot, each cached by config hash.

A run has one or more passes. Without `variants` there is one pass over `dataset`; an experiment can
list `variants` (each an optional `label` plus config overrides merged into the run's config, e.g. another
`dataset` or `generate.pairing` level), and every variant runs the data stages on its own, while one
plot stage draws all of them into shared figures (night_vs_acdc, pairing_ablation)."""
from __future__ import annotations

import json
import logging
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pairedgta.cache import MANIFEST, StageCache, canonical_json
from pairedgta.conditions import build_condition_grid
from pairedgta.config_checks import check_run_config
from pairedgta.datasets import open_dataset
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.models import model_config
from pairedgta.stages import evaluate, generate, plot, pseudolabel
from pairedgta.stages.common import STAGES, Context, StageResult
from pairedgta.stages.plot import PassResult
from pairedgta.tracking import Tracker, evaluation_metrics

log = logging.getLogger("pairedgta")
MISSING = "???"


def _as_list(value: Any, key: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def check_config(cfg: dict[str, Any]) -> tuple[list[str], set[str]]:
    stages = _as_list(cfg.get("stages"), "stages")
    force = set(_as_list(cfg.get("force"), "force"))
    for key, values in (("stages", stages), ("force", force)):
        bad = [s for s in values if s not in STAGES]
        if bad:
            raise ConfigError(f"{key}={bad} names unknown stage(s); stages are {', '.join(STAGES)}")
    if cfg.get("device") not in ("cpu", "cuda", "auto") and not str(cfg.get("device")).startswith("cuda:"):
        raise ConfigError(f"device={cfg.get('device')!r}; use cpu, cuda or auto")
    return stages, force


def evaluated_models(cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """`models=[a,b]` wins over the single `model` group; the device comes from the top-level key."""
    names = cfg.get("models")
    if names:
        return [model_config(str(n), device=cfg["device"]) for n in _as_list(names, "models")]
    model = dict(cfg["model"])
    model["device"] = cfg["device"]
    return [model]


# -- passes ---------------------------------------------------------------------------------------
def _merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in overrides.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) and k != "dataset" else v
    return out


def pass_configs(container: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(label, config) per pass: the run's config, or one per entry of `variants` (label + overrides;
    a variant's `dataset` replaces the dataset node as a whole)."""
    variants = container.get("variants")
    if not variants:
        return [(str(container["dataset"].get("name", "dataset")), container)]
    out, labels = [], set()
    for i, v in enumerate(variants):
        if not isinstance(v, dict):
            raise ConfigError(f"variants[{i}] must be a mapping (label + config overrides), got {v!r}")
        v = dict(v)
        label = str(v.pop("label", None) or f"variant{i}")
        if label in labels:
            raise ConfigError(f"variants: duplicate label {label!r}")
        labels.add(label)
        cfg = _merge(container, v)
        cfg.pop("variants", None)
        out.append((label, cfg))
    return out


def _root_key(container: dict[str, Any], dataset: dict[str, Any], variant: bool) -> str:
    """The config key a user sets to fill a dataset's root: dataset.root, or the top-level node a
    variant's dataset interpolates (e.g. acdc.root)."""
    if variant:
        for k, v in container.items():
            if k not in ("dataset", "variants") and isinstance(v, dict) and v == dataset:
                return f"{k}.root"
    return "dataset.root"


def check_roots(container: dict[str, Any]) -> None:
    """Every dataset a pass reads needs a root, before anything is computed: one line naming the key."""
    for label, cfg in pass_configs(container):
        d = cfg["dataset"]
        if d.get("root") != MISSING:
            continue
        key = _root_key(container, d, bool(container.get("variants")))
        if d.get("kind") == "acdc":
            from pairedgta.datasets.acdc import missing_root_message

            raise ConfigError(missing_root_message(key))
        raise ConfigError(f"{key} is required for dataset={d.get('name')}; set {key}=PATH")


def open_pass(label: str, cfg: dict[str, Any], cache: StageCache, stages: list[str], force: set[str],
              results: dict[str, Any], needs: set[str]) -> tuple[Context, PassResult]:
    dcfg = cfg["dataset"]
    if dcfg.get("kind") == "acdc":
        from pairedgta.datasets.acdc import open_acdc

        dataset, grid = open_acdc(dcfg)
        ctx = Context(cfg=cfg, grid=grid, cache=cache, stages=stages, force=force, results=results)
        log.info("pass %s: ACDC %s, %d pairs (%d skipped without reference)", label, dcfg.get("condition"),
                 len(dataset), dataset.skipped_without_reference)
        return ctx, PassResult(label, cfg, grid, dataset, f"external:{dataset.fingerprint()}")
    grid = build_condition_grid(cfg["conditions"])
    ctx = Context(cfg=cfg, grid=grid, cache=cache, stages=stages, force=force, results=results)
    if dcfg.get("kind") == "generated" and not dcfg.get("root"):
        if not ({"generate", "pseudolabel", "evaluate"} & (needs | set(stages))):
            return ctx, PassResult(label, cfg, grid)  # e.g. the cost figure from a given CSV
        gen = generate.run(ctx)
        results["generate"] = gen
        dataset = open_dataset(dcfg, grid, root=gen.path)
        return ctx, PassResult(label, cfg, grid, dataset, f"generate:{gen.key}", generate=gen)
    if "generate" in stages:
        log.info("generate: skipped, dataset.root=%s is an existing dataset", dcfg.get("root"))
    dataset = open_dataset(dcfg, grid)
    return ctx, PassResult(label, cfg, grid, dataset, f"external:{dataset.fingerprint()}")


def _evaluated_conditions(ctx: Context, reference: str) -> list[str]:
    """The condition list evaluate hashes (as evaluate.run derives it from evaluate.conditions)."""
    wanted = (ctx.cfg.get("evaluate") or {}).get("conditions")
    return [c for c in ctx.grid.names if c in wanted or c == reference] if wanted else list(ctx.grid.names)


def _model_name(result: StageResult) -> str:
    return str(json.loads((result.path / MANIFEST).read_text())["config"]["model"]["name"])


def cached_evaluations(ctx: Context, p: PassResult) -> list[StageResult]:
    """Every cached evaluate output of this pass's dataset and pseudo-labels under the same metric
    settings and conditions (the models of earlier runs, e.g. a multirun over `model=`): the newest
    per model, for the models this run did not evaluate itself."""
    assert p.pseudo is not None and p.dataset is not None
    root = ctx.cache.root / "evaluate"
    if not root.is_dir():
        return []
    want_inputs = {"dataset": p.dataset_key, "pseudolabel": p.pseudo.key}
    settings = json.loads(canonical_json(evaluate.metric_settings(ctx.cfg, ctx.grid.names, p.dataset.reference)))
    conditions = _evaluated_conditions(ctx, p.dataset.reference)
    own = {_model_name(e) for e in p.evaluations}
    found: dict[str, tuple[float, StageResult]] = {}
    for manifest_path in root.glob(f"*/{MANIFEST}"):
        d = manifest_path.parent
        if d.name.startswith("."):
            continue
        try:
            m = json.loads(manifest_path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        cfg = m.get("config") or {}
        if m.get("inputs") != want_inputs or cfg.get("metric") != settings or cfg.get("conditions") != conditions:
            continue
        name = str((cfg.get("model") or {}).get("name"))
        if name in own:
            continue
        mtime = manifest_path.stat().st_mtime
        if name not in found or mtime > found[name][0]:
            found[name] = (mtime, StageResult("evaluate", d.name, d, hit=True))
    return [r for _, r in sorted(found.values(), key=lambda t: t[1].key)]


def run(cfg: DictConfig) -> dict[str, Any]:
    if OmegaConf.is_missing(cfg.dataset, "root") and cfg.dataset.get("kind") != "acdc":
        raise ConfigError(f"dataset.root is required for dataset={cfg.dataset.name}; set dataset.root=PATH")
    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert isinstance(container, dict)
    check_run_config(container)
    check_roots(container)
    stages, force = check_config(container)
    cache = StageCache(container["cache_dir"])
    models = evaluated_models(container)
    tracking = container.get("tracking") or {}
    tracker = Tracker(tracking.get("uri", "sqlite:///outputs/mlflow.db"), str(tracking.get("experiment_name") or container.get("name", "default")), bool(tracking.get("enabled", True)))

    if container["dataset"].get("kind") == "cityscapes":
        # a sanity check of the models themselves (wrong preprocessing shows up here), not a paired run
        from pairedgta.stages import cityscapes_val

        ctx = Context(cfg=container, grid=build_condition_grid(container["conditions"]), cache=cache, stages=stages, force=force)
        with tracker.run(str(container.get("name", "run"))):
            tracker.params({k: v for k, v in container.items() if k not in ("hydra",)})
            return cityscapes_val.run(ctx, models, tracker)

    plotting = "plot" in stages
    needs = plot.needed_stages(container) if plotting else set()
    collect = plotting and bool((container.get("plot") or {}).get("collect_cached"))
    run_pseudo = bool({"pseudolabel", "evaluate"} & set(stages)) or "pseudolabel" in needs or "evaluate" in needs
    run_eval = "evaluate" in stages or "evaluate" in needs
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"dataset": None, "evaluate": {}, "plot": None, "stages": results.setdefault("stages", [])}
    configs = pass_configs(container)
    multi = len(configs) > 1
    passes: list[tuple[Context, PassResult]] = []
    for label, pcfg in configs:
        ctx, p = open_pass(label, pcfg, cache, stages, force, results, needs)
        passes.append((ctx, p))
        if p.dataset is not None:
            log.info("dataset %s%s: %d groups, reference %s", p.dataset.name, f" ({label})" if multi else "",
                     len(p.dataset), p.dataset.reference)
            summary["dataset"] = summary["dataset"] or str(p.dataset.root)
            if multi:
                summary.setdefault("datasets", {})[label] = str(p.dataset.root)
    if not (run_pseudo or plotting):
        return summary
    with tracker.run(str(container.get("name", "run"))):
        tracker.params({k: v for k, v in container.items() if k not in ("hydra",)})
        first = passes[0][1]
        tracker.tags({"dataset": first.dataset.name if first.dataset else "none",
                      "dataset_key": str(first.dataset_key), "passes": ", ".join(p.label for _, p in passes)})
        for ctx, p in passes:
            if p.dataset is None or not run_pseudo:
                continue
            p.pseudo = pseudolabel.run(ctx, p.dataset, str(p.dataset_key))
            summary["pseudolabel"] = str(p.pseudo.path) if not multi else summary.get("pseudolabel", str(p.pseudo.path))
            tracker.artifacts([p.pseudo.path / "histogram.csv", p.pseudo.path / "quality.csv"],
                              "pseudolabel" if not multi else f"pseudolabel/{p.label}")
            if not run_eval:
                continue
            for model_cfg in models:
                name = model_cfg["name"] if not multi else f"{p.label}/{model_cfg['name']}"
                try:
                    result = evaluate.run(ctx, p.dataset, str(p.dataset_key), p.pseudo, model_cfg)
                except PairedGTAError as exc:
                    if collect and "evaluate" not in stages and "no cached output" in str(exc):
                        log.info("evaluate [%s]: not cached; plot collects the cached models only", model_cfg["name"])
                        continue
                    raise
                p.evaluations.append(result)
                with tracker.run(name, nested=True):
                    tracker.params({"model": model_cfg, "metric": ctx.cfg["metric"], "reference_model": ctx.cfg["reference_model"]})
                    tracker.tags({"evaluate_hash": result.key, "cache_hit": str(result.hit), "dataset": p.dataset.name,
                                  "pass": p.label})
                    tracker.metrics(evaluation_metrics(result.path))
                    tracker.artifacts(sorted(result.path.glob("*.csv")) + [result.path / "summary.json"], "evaluate")
                summary["evaluate"][name] = str(result.path)
            if collect:
                extra = cached_evaluations(ctx, p)
                if extra:
                    log.info("plot: collected %d cached evaluation(s) of this dataset: %s", len(extra),
                             ", ".join(_model_name(e) for e in extra))
                    p.evaluations.extend(extra)
            if plotting and "evaluate" in needs and not p.evaluations:
                raise ConfigError(
                    f"plot: no evaluation of dataset {p.label} to draw; run it first, e.g. stages=[evaluate,plot]"
                )
        if plotting:
            figures = plot.run(passes[0][0], [p for _, p in passes])
            summary["plot"] = str(figures.path)
            tracker.artifacts(sorted(q for q in figures.path.iterdir() if q.suffix in (".png", ".pdf", ".csv", ".md", ".tex")), "figures")
            metrics_file = figures.path / "metrics.json"
            if metrics_file.is_file():
                tracker.metrics(json.loads(metrics_file.read_text()))
    return summary
