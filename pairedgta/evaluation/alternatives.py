"""The trial of alternative set-ups, for any task: score a model as configured and under each alternative a user
could type as one change, on the same few labelled clean images, and name the alternative that clearly beats it.

A task supplies its candidates (the change as typed, e.g. `model.channels=bgr`, and the model keys it sets) and
one score callable that gets them all at once (configured first), so that it may batch them; it returns one score
per candidate, a number or a row of its own with a `score` (NaN: the candidate could not be scored). Segmentation's
are in pairedgta/evaluation/setup_check.py (channel order, scale, mean/std, label space; clean GT mIoU); another
task (detection) supplies its own candidates and score function.

The rule, the same for every task and every configured score (`clearly_beats`): an alternative clearly beats the
configured set-up when, on the same images, its score is at least RATIO x and at least MARGIN above the configured
one. Both: the ratio alone would name +0.01 over a configured 0.02 (noise on a few images), the margin alone 0.45
over 0.40. Measured on 4 clean images of the main job's scenes: the zoo's models set up right (demo_ddrnet, _pidnet,
_deeplabv3plus, _segformer, their noaug and short variants) have no alternative above 0.94x their own (0.98x on the
synthetic street, out of their domain): silent. Named: a researcher's LR-ASPP fed RGB instead of its BGR (0.17
against 0.26: 1.5x, +0.09), demo_segformer fed BGR (0.42 against 0.54: 1.3x), tests/test_setup_check.py's BGR
network fed RGB (0.15 against 0.62). Not named: the colour-augmented CNNs fed BGR, which lose little (demo_ddrnet
0.47 against 0.50, demo_deeplabv3plus 0.40 against 0.47: 1.2x)."""
from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

RATIO = 1.25   # an alternative clearly beats the configured set-up at >= RATIO x its score ...
MARGIN = 0.05  # ... and >= MARGIN above it, in absolute terms (scores in [0, 1]: mIoU, AP)
CONFIGURED = "configured"  # the `change` of the configured set-up


@dataclass(frozen=True)
class Candidate:
    """One set-up: `change` as the user would type it (CONFIGURED for the configured one) and the model keys it
    sets (`{"channels": "bgr"}`; empty for the configured one). A task may subclass it to carry what it runs."""

    change: str
    overrides: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Outcome:
    candidate: Candidate
    score: float   # NaN: not scored (its forward failed)
    row: Any = None  # the task's own row, when the score callable returned one


@dataclass(frozen=True)
class Verdict:
    """The configured outcome and the alternatives', in the order tried."""

    configured: Outcome
    alternatives: tuple[Outcome, ...]

    @property
    def outcomes(self) -> tuple[Outcome, ...]:
        return (self.configured, *self.alternatives)

    @property
    def best(self) -> Outcome | None:
        """The alternative with the highest score (the first on ties), None when none was scored."""
        scored = [o for o in self.alternatives if not math.isnan(o.score)]
        return max(scored, key=lambda o: o.score) if scored else None

    @property
    def better(self) -> Outcome | None:
        """The best alternative when it clearly beats the configured set-up, else None."""
        best = self.best
        return best if best is not None and clearly_beats(best.score, self.configured.score) else None


def clearly_beats(score: float, configured: float, ratio: float = RATIO, margin: float = MARGIN) -> bool:
    """`score` >= ratio x `configured` and >= `configured` + margin (both finite)."""
    if not (math.isfinite(score) and math.isfinite(configured)):
        return False
    eps = 1e-9  # 0.11 against 0.06 is +0.05, whatever the floats' last bits say
    return score >= ratio * configured - eps and score >= configured + margin - eps


def _value(result: Any) -> float:
    value = result if isinstance(result, (int, float)) else getattr(result, "score")
    return math.nan if value is None else float(value)


def trial(candidates: Sequence[Candidate], score: Callable[[Sequence[Candidate]], Sequence[Any]]) -> Verdict:
    """`candidates` (the configured set-up first) scored by `score`, all in one call: the verdict."""
    if not candidates:
        raise ValueError("trial: no candidates (the configured set-up comes first)")
    results = list(score(candidates))
    if len(results) != len(candidates):
        raise ValueError(f"trial: {len(results)} scores for {len(candidates)} candidates")
    outcomes = [Outcome(c, _value(r), None if isinstance(r, (int, float)) else r) for c, r in zip(candidates, results)]
    return Verdict(outcomes[0], tuple(outcomes[1:]))


def record(outcome: Outcome | None, score_name: str = "score") -> dict[str, Any] | None:
    """An outcome as summary.json keeps it: {"setup": the change as typed, "overrides": the keys, score_name: ...}."""
    if outcome is None:
        return None
    return {"setup": outcome.candidate.change, "overrides": dict(outcome.candidate.overrides),
            score_name: outcome.score}


@contextlib.contextmanager
def quiet(*loggers: str) -> Iterator[None]:
    """The loggers `loggers` say nothing below ERROR inside the block: a trial of set-ups the user never chose
    prints nothing about them (a label space's name mismatches, say)."""
    saved = [(logging.getLogger(name), logging.getLogger(name).level) for name in loggers]
    for logger, _ in saved:
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for logger, level in saved:
            logger.setLevel(level)


def report(stage: str, name: str, summary: dict[str, Any], score: str, label: str, threshold: float, table: str,
           path: Any) -> tuple[dict[str, float], dict[str, Any]]:
    """A model check's lines, the same for every task: its table, then its warning, or that it is set up right;
    -> (its MLflow metrics, its entry in the run's summary). `score`: the summary's key of the configured score
    (clean_miou, clean_ap50), `label` its words ("clean GT mIoU")."""
    log = logging.getLogger("pairedgta.model_check")
    value = summary[score]
    tried = " and with each alternative" if summary.get("alternatives") else ""
    log.info("%s [%s]: %s on %d %s image(s) of %s, as configured%s (%s):\n%s", stage, name, label,
             summary["n_images"], summary["condition"], summary["where"], tried, path, table)
    if summary["warning"]:
        log.warning("%s", summary["warning"])
    elif value is not None:
        log.info("%s [%s]: %s %.2f >= %.2f, and no alternative clearly beats it: set up right", stage, name, label,
                 value, threshold)
    metrics = {f"{stage}/{score}": value} if value is not None else {}
    return metrics, {score: value, "best_alternative": summary["best_alternative"], "better": summary.get("better"),
                     "warning": summary["warning"], "path": str(Path(path).parent)}


__all__ = ["RATIO", "MARGIN", "CONFIGURED", "Candidate", "Outcome", "Verdict", "clearly_beats", "trial", "record",
           "report", "quiet"]
