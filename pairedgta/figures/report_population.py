"""Which models a model report places its subject among (the figure `model_report`, +experiment=model_report).

The subject is the run's `model` (a zoo member, a paper model or a researcher's through a model source); the population
is `report.population`, or the offline zoo where that is null. A run that draws the figure evaluates the subject and
its population, whatever `models` or a command-line `model=` say (pairedgta/stages/planning.py: run_models), so the
population's evaluate entries are cache hits from one subject to the next. Neither the subject nor the reference
model (whose pseudo-labels xi counts: it would grade itself) is counted in the population.

Light on purpose: the planner reads it before any stage runs, and the plot stage's key on a cached run."""
from __future__ import annotations

from typing import Any, Mapping

from pairedgta.errors import ConfigError

FIGURE = "model_report"
EXAMPLE = "report.population=[demo_ddrnet,demo_pidnet]"


def zoo(task: str | None = None) -> list[str]:
    """The offline zoo of the task: the `models` of the option file its declaration names (pairedgta/tasks.py `zoo`:
    experiment=zoo's list for segmentation, the detection task's own); the default task's without one."""
    import yaml

    from pairedgta import tasks
    from pairedgta.configs import CONFIG_DIR

    declared = tasks.get(task or tasks.DEFAULT)
    return [str(m) for m in yaml.safe_load((CONFIG_DIR / declared.zoo).read_text())["models"]]


def draws_report(run: Any) -> bool:
    """Whether the run draws a model report (pairedgta.schema.RunConfig)."""
    from pairedgta import tasks
    from pairedgta.figures import figures_of
    from pairedgta.schema import as_dict

    return bool(set(tasks.report_figures()) & set(figures_of(as_dict(run))))


def subject_name(model_cfg: Mapping[str, Any]) -> str:
    """The `model` group's name as the stages use it (a source model's file name where it gives none)."""
    from pairedgta.models import with_defaults

    return str(with_defaults(dict(model_cfg))["name"])


def members(run: Any, subject: str, reference: str) -> tuple[list[str], list[str]]:
    """-> (the population, the listed names left out of it: the subject, the reference). One line when the subject is
    the reference model or no model is left to place it against."""
    listed = list(run.report.population) if run.report.population is not None else zoo(str(run.task))
    where = "report.population" if run.report.population is not None else "report.population (null: the offline zoo)"
    if subject == reference:
        raise ConfigError(f"{FIGURE}: the model to report is {subject}, the reference model, whose pseudo-labels xi "
                          f"counts (it would grade itself); choose another, e.g. model=onnx model.path=net.onnx or "
                          f"model=demo_ddrnet")
    kept = [n for n in listed if n not in (subject, reference)]
    if not kept:
        raise ConfigError(f"{where}={listed}: no model to place {subject} against besides itself and the reference "
                          f"model {reference}; list at least one, e.g. {EXAMPLE}")
    return kept, [n for n in listed if n in (subject, reference)]


def evaluations(p: Any, opts: Any, figure: str, what: str) -> tuple[str, str, list[str], list[str], list[Any]]:
    """-> (subject, reference, listed population, evaluated population, [subject's, population's evaluations]) on
    pass `p`; one line when the subject or the whole population has no evaluation there."""
    run = opts.run
    subject = subject_name(run.model)
    reference = p.pseudo.reference_model() if p.pseudo is not None else str(run.reference_model or subject)
    listed, _ = members(run, subject, reference)
    by_model = {e.model: e for e in p.evaluations}
    if subject not in by_model:
        raise ConfigError(f"plot.figures: {figure} has no evaluation of the {what} to report, {subject}, on dataset "
                          f"{p.label}; run it with stages=[evaluate,plot]")
    population = [m for m in listed if m in by_model]
    if not population:
        raise ConfigError(f"plot.figures: {figure} found no evaluation of report.population ({', '.join(listed)}) on "
                          f"dataset {p.label}; run it with stages=[evaluate,plot]")
    return subject, reference, listed, population, [by_model[m] for m in [subject, *population]]


def cache_key(passes: Any, opts: Any) -> tuple[dict[str, Any], dict[str, str]]:
    """What the figure reads beyond the evaluations (the plot stage's key): who the subject is and whom it is placed
    against (the same evaluations can hold another subject's report), the report's sizes and the bootstrap."""
    run = opts.run
    subject = subject_name(run.model)
    reference = passes[0].pseudo.reference_model() if passes and passes[0].pseudo is not None else run.reference_model
    population, _ = members(run, subject, str(reference or subject))
    boot = run.metric.bootstrap
    return {"subject": subject, "population": population, "worst_conditions": run.report.worst_conditions,
            "worst_cases": run.report.worst_cases, "resamples": boot.resamples, "confidence": boot.confidence,
            "seed": boot.seed}, {}


__all__ = ["FIGURE", "zoo", "draws_report", "subject_name", "members", "cache_key"]
