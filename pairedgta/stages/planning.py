"""Pass planning: what a run computes, over which datasets, with which models.

A run has one or more passes. Without `variants` there is one pass over `dataset`; an experiment can
list `variants` (each an optional `label` plus config overrides merged into the run's config, e.g. another
`dataset` or `generate.pairing` level), and every variant runs the data stages on its own, while one
plot stage draws all of them into shared figures (night_vs_acdc, pairing_ablation).

Models reach a run through one channel: the composed `model` group (with the user's `model.<key>=`
overrides) serves wherever the run uses that model, evaluated or as reference; every other name in
`models` or `reference_model` is read from the same config group and `model_overrides.<name>` applies.

Which stages run, and where a pass keeps their results, follows from pairedgta/stage_registry.py: this module
names no stage.
"""
from __future__ import annotations

import copy
import functools
import logging
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Protocol

from pairedgta.conditions import ConditionGrid, build_condition_grid
from pairedgta.configs import merge_variant
from pairedgta.datasets import DATASETS, PairedDataset, image_notes, missing_root_message, open_dataset
from pairedgta.errors import ConfigError
from pairedgta.models import check_model_config, for_kind, model_config, with_defaults
from pairedgta import schema, stage_registry, tasks
from pairedgta.schema import MISSING
from pairedgta.stages.common import Context
from pairedgta.tracking.recorder import Recorder

log = logging.getLogger("pairedgta")


@dataclass
class PassResult:
    """One dataset variant of the run and its stage results: each stage's result in the slot its spec names
    (pairedgta/stage_registry.py), read and set as an attribute (`p.generate`, `p.pseudo`, `p.evaluations`)."""

    label: str
    cfg: dict[str, Any]
    grid: ConditionGrid
    dataset: PairedDataset | None = None
    dataset_key: str | None = None
    results: dict[str, Any] = field(default_factory=stage_registry.empty_slots)

    def __post_init__(self) -> None:
        _install_slots()  # a stage registered since import (a test's toy stage) gets its attribute too

    @functools.cached_property
    def run(self) -> schema.RunConfig:
        """The pass's config, typed (pairedgta/schema.py)."""
        return schema.parse(self.cfg)

    @property
    def pairing(self) -> dict[str, float]:
        return schema.as_dict(self.run.generate.pairing)

    def record_dataset(self, recorder: Recorder) -> None:
        """The pass's dataset as an MLflow dataset input of the active run."""
        assert self.dataset is not None
        recorder.dataset(self.dataset.name, self.dataset.root, str(self.dataset_key).split(":", 1)[-1],
                         {"pass": self.label, "dataset_key": str(self.dataset_key), "reference": self.dataset.reference})

    def reading(self) -> Any:
        """A context for the stages that read this pass's images: a blank image, or one converted on reading,
        is one warning for the dataset (a few files named, and the count) when they are done."""
        return image_notes(f"dataset {self.label}")


class _Slot:
    """`p.<slot>` of a pass: its entry in `p.results`, the result of the stage that declares that slot."""

    def __init__(self, slot: str) -> None:
        self.slot = slot

    def __get__(self, p: PassResult | None, owner: type | None = None) -> Any:
        if p is None:
            return self
        try:
            return p.results[self.slot]
        except KeyError:
            raise AttributeError(f"no stage of this run declares the slot {self.slot!r}") from None

    def __set__(self, p: PassResult, value: Any) -> None:
        p.results[self.slot] = value


def _install_slots() -> None:
    for spec in stage_registry.slotted():
        slot = str(spec.slot)
        if isinstance(PassResult.__dict__.get(slot), _Slot):
            continue
        if hasattr(PassResult, slot) or slot in PassResult.__dataclass_fields__:
            raise ValueError(f"stage {spec.name}: slot={slot!r} is already an attribute of a pass; name another slot")
        setattr(PassResult, slot, _Slot(slot))


_install_slots()


@dataclass
class Plan:
    stages: list[str]
    force: set[str]
    needs: set[str]  # upstream stages the requested stages' config makes them read (the figures')
    models: Any = None  # RunModels, once resolved: checked for availability before a new dataset is rendered
    task: tasks.Task = tasks.TASKS[tasks.DEFAULT]  # whose work (pseudo-labeller, evaluation, checks) the stages call

    def runs(self, name: str) -> bool:
        """Whether a stage runs: listed in `stages`, read by a listed stage's config, or upstream of either."""
        return name in stage_registry.with_upstream([*self.stages, *self.needs])

    def steps(self, *scopes: str) -> list[stage_registry.StageSpec]:
        """The stages of these scopes that run, in the order they run."""
        return [s for s in stage_registry.in_scope(*scopes) if self.runs(s.name)]

    @property
    def plotting(self) -> bool:
        """Whether a stage over every pass (the figures) runs: it reads what the pass stages leave."""
        return bool(self.steps("run"))


@dataclass
class RunModels:
    evaluated: list[dict[str, Any]]
    reference: dict[str, Any]


@dataclass
class RunState:
    """What the stages of a run share beyond their context: the plan, the models, the MLflow recorder, the
    summary the run returns and the nested runs of the models (which the plot stage gives their own figures)."""

    plan: Plan
    models: RunModels
    recorder: Recorder     # in-process or background (pairedgta/tracking/recorder.py)
    experiment: str
    multi: bool            # several passes: names carry the pass label
    summary: dict[str, Any]
    model_runs: list[tuple[str | None, str, str]] = field(default_factory=list)  # (nested run, model, pass)
    passes: list[PassResult] = field(default_factory=list)  # every pass of the run, as opened so far


def make_plan(cfg: dict[str, Any], run: schema.RunConfig) -> Plan:
    from pairedgta import figures

    stages, force = list(run.stages), set(run.force)
    device = run.device
    if device not in ("cpu", "cuda", "auto") and not device.startswith("cuda:"):
        raise ConfigError(f"device={device!r}; use cpu, cuda or auto")
    check_cuda(device)
    sourced = figures.sourced(cfg)
    over_passes = [s.name for s in stage_registry.in_scope("run")]
    if sourced and not set(stages) <= set(over_passes):  # e.g. Table 1 from plot.table_csv: a file, not this run's data
        raise ConfigError(f"{', '.join(sorted(set(sourced.values())))} draws {', '.join(sourced)} from that file and runs no "
                          f"data stage; use stages=[{','.join(over_passes)}] (stages={stages})")
    needs = set().union(*(stage_registry.spec(name).needs_of(cfg) for name in stages))
    if not sourced:
        check_renderer(cfg)
    task = tasks.get(run.task)
    if set(stages) & set(over_passes):  # the figures are drawn: each must be of the run's task
        tasks.check_figures(task, list(run.plot.figures))
    return Plan(stages, force, needs, task=task)


def check_renderer(cfg: dict[str, Any]) -> None:
    """A run that reads a generated dataset needs its renderer's software here (Blender as a module for
    renderer=blender: its version is part of the generate key): one line before the record opens or any stage
    writes, not when the generate stage starts."""
    from pairedgta.render import renderer_versions

    if any((c.get("dataset") or {}).get("root") is None for _, c in pass_configs(cfg)):
        renderer_versions((cfg.get("renderer") or {}).get("backend"))


def check_cuda(device: str) -> None:
    """device=cuda[:N] needs that GPU here: said before anything runs, not as torch's driver traceback."""
    if not device.startswith("cuda"):
        return
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    index = int(device.split(":", 1)[1]) if ":" in device and device.split(":", 1)[1].isdigit() else 0
    if count == 0:
        raise ConfigError(f"device={device}: no CUDA GPU is visible here (torch.cuda.is_available() is False); "
                          "use device=cpu, or device=auto to take a GPU where there is one")
    if index >= count:
        raise ConfigError(f"device={device}: this machine has {count} CUDA GPU(s) (cuda:0..cuda:{count - 1})")


class Step(Protocol):
    """A stage module's `step`, the one entry point the app calls for every stage (pairedgta/stage_registry.py):
    `p` is the pass (scopes dataset, pass and check), or the first pass for a stage over every pass (scope run,
    which reads `state.passes`). It keeps its result in its slot of `p` and records it in `state`."""

    def __call__(self, ctx: Context, p: PassResult, state: RunState) -> None:
        ...


# -- models -------------------------------------------------------------------------------------------
def model_group_overridden(task_overrides: list[str] | None) -> bool:
    """Whether the user chose the `model` group on the command line (`model=x`, also in a sweep)."""
    for o in task_overrides or []:
        key = o.split("=", 1)[0].lstrip("+~")
        if key == "model":
            return True
    return False


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def run_models(run: schema.RunConfig, model_chosen: bool = False) -> RunModels:
    """The composed config of every model the run evaluates and of its reference model.

    `models=[...]` lists the evaluated models; when the user chose `model=` on the command line (e.g. a
    sweep `-m model=a,b`), the chosen model replaces that list for this job. A run that draws the model report
    evaluates the chosen model and its population instead (pairedgta/figures/report_population.py), the model first."""
    from pairedgta.figures import report_population

    primary = for_kind(run.model, tasks.get(run.task).model_kind)  # model=onnx is a detector under task=detection
    if not primary.get("name"):  # a source model named by its file (pairedgta/models: default_name)
        primary = with_defaults(primary)
    names = list(run.models or [])
    reference = run.reference_model or primary["name"]
    if report_population.draws_report(run):
        population, left_out = report_population.members(run, primary["name"], reference)
        for name in left_out:
            log.info("report: %s is left out of the population (%s)", name,
                     "the model reported" if name == primary["name"] else "the reference model: not ranked")
        if names:
            log.info("report: %s placed against report.population; models=%s is not evaluated", primary["name"], names)
        log.info("report: %s placed against %d model(s): %s", primary["name"], len(population), ", ".join(population))
        names = [primary["name"], *population]
    elif names and model_chosen and names != [primary["name"]]:
        log.info("model=%s replaces the experiment's models=%s for this job", primary["name"], names)
        names = [primary["name"]]
    names = names or [primary["name"]]
    used = list(dict.fromkeys(names + [reference]))
    overrides = dict(run.model_overrides)
    unused = [n for n in overrides if n not in used]
    if unused:
        raise ConfigError(
            f"model_overrides.{unused[0]}: model '{unused[0]}' is not used by this run (it uses {', '.join(used)}); "
            "remove the override or add the model to models=[...]"
        )
    resolved: dict[str, dict[str, Any]] = {}
    for name in used:
        base = primary if name == primary["name"] else model_config(name)
        extra = overrides.get(name) or {}
        if not isinstance(extra, dict):
            raise ConfigError(f"model_overrides.{name} must be a mapping of model keys, got {extra!r}")
        merged = with_defaults(_merge(base, extra))  # the hashed config names every shared option
        check_model_config(merged, "model" if name == primary["name"] and not extra else f"model_overrides.{name}")
        resolved[name] = merged
    tasks.check_models(tasks.get(run.task), [*(("model", resolved[n]) for n in names),
                                             ("reference_model", resolved[reference])])
    return RunModels([resolved[n] for n in names], resolved[reference])


# -- passes -------------------------------------------------------------------------------------------
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
        cfg = merge_variant(container, v)
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
    """Every dataset a pass reads needs a root, before anything is computed: one line naming the key.
    A run that only draws figures from files given to it (plot.table_csv, plot.frame_counts_csv) reads none."""
    from pairedgta.figures import sourced

    stages = list(container.get("stages") or [])
    if sourced(container) and stages and all(stage_registry.spec(s).scope == "run" for s in stages):
        return
    for _label, cfg in pass_configs(container):
        d = cfg["dataset"]
        root = d.get("root")
        if root == MISSING:
            key = _root_key(container, d, bool(container.get("variants")))
            raise ConfigError(missing_root_message(d, key))
        if root is not None and not Path(str(root)).expanduser().is_dir():
            # before the generated pass renders for minutes; named by the key the user typed (acdc.root)
            key = _root_key(container, d, bool(container.get("variants")))
            what = "is a file, not a directory" if Path(str(root)).expanduser().exists() else "does not exist"
            raise ConfigError(f"{key}={root} {what}; point it at the {d.get('name', 'dataset')} folder "
                              f"(the one that holds its images)")


def open_pass(label: str, ctx: Context, plan: Plan) -> PassResult:
    """The pass, with its dataset open when `dataset.root` names one; a stage of scope "dataset" (generate)
    opens a generated one (`dataset.root: null`) in its step."""
    cfg, grid = ctx.cfg, ctx.grid
    dcfg = dict(cfg["dataset"])
    if not DATASETS.meta(dcfg.get("kind")).get("paired"):
        checks = ",".join(s.name for s in stage_registry.in_scope("check") if not s.needs)  # those reading no pass
        raise ConfigError(
            f"dataset={dcfg.get('name')} is not a paired dataset: it feeds the model check "
            f"(+experiment=cityscapes_val_check, stages=[{checks}]), not {', '.join(plan.stages)}"
        )
    if not plan.steps("dataset", "pass") or dcfg.get("root") is None:
        # figures drawn from given files (cost.csv, the authors' CSVs) read no dataset
        return bare_pass(label, ctx)
    dataset = open_dataset(dcfg, grid)
    return _typed(PassResult(label, cfg, dataset.grid or grid, dataset, f"external:{dataset.fingerprint()}"), ctx)


def bare_pass(label: str, ctx: Context) -> PassResult:
    """A pass with no dataset open (yet): a generated one before its step, a check's, one of figures from files."""
    return _typed(PassResult(label, ctx.cfg, ctx.grid), ctx)


def pass_context(cfg: dict[str, Any], cache: Any, plan: Plan, results: dict[str, Any],
                 run: schema.RunConfig | None = None) -> Context:
    """`run`: the typed config where the caller has it already (the run's own, for its only pass): the config
    is parsed once per pass."""
    typed = run if run is not None else schema.parse(cfg)
    return Context(cfg=cfg, run=typed, grid=build_condition_grid(cfg["conditions"]), cache=cache, stages=plan.stages,
                   force=plan.force, results=results)


def _typed(result: PassResult, ctx: Context) -> PassResult:
    result.__dict__["run"] = ctx.run  # PassResult.run (a cached property) is the context's: not parsed again
    return result


__all__ = ["PassResult", "Step", "Plan", "RunModels", "RunState", "make_plan", "run_models", "model_group_overridden", "pass_configs",
           "check_roots", "open_pass", "bare_pass", "pass_context"]
