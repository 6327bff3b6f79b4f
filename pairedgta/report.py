"""The table a run ends with: mean xi per model x adverse condition, read back from each evaluation's
`summary.json` (a cached rerun reads JSON, no torch), the best model of each condition marked, as
evaluation harnesses print their leaderboards. The reference model, whose pseudo-labels xi counts, is
graded on its own predictions: its row is shown last, labelled as the reference, and never marked. A task whose
summaries count what each mean rests on (`xi_support`; detection: the reference boxes of the supported classes)
gets that count under each column header, as few boxes move a cell by whole hundredths. Below the table,
one line per model whose label space cannot predict some Cityscapes classes (`unpredictable_lines`)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from pairedgta import tasks
from pairedgta.evaluation.entry import SUMMARY

REFERENCE_TAG = " (reference)"


def xi_lines(evaluations: dict[str, str], reference: str | None = None, width: int = 9) -> list[str]:
    """Rows `model  value value ...`, one column per adverse condition (short names: Day-RAIN, ...),
    the column's best among the models other than the reference marked `*`; [] when no evaluation has a
    summary. `reference`: the clean condition, left out of the columns."""
    means: dict[str, dict[str, float]] = {}
    title = "mean xi"
    teachers: set[str] = set()
    support: dict[str, dict[str, int]] = {}  # per model, what its mean rests on per condition (Task.support)
    support_label = ""
    own: set[str] = set()  # evaluations of the model whose pseudo-labels they are scored against
    for name, path in evaluations.items():
        summary = Path(path) / SUMMARY
        if summary.is_file():
            data = json.loads(summary.read_text())
            title = tasks.of_entry(data).title  # the task whose evaluate work wrote it
            teacher = str(data.get("reference_model"))
            teachers.add(teacher)
            if str(data.get("model", name.rsplit("/", 1)[-1])) == teacher:
                own.add(name)
            means[name] = {c: v for c, v in (data.get("xi_mean") or {}).items() if c != reference}
            if data.get("xi_support") is not None:
                support[name] = data["xi_support"]
                support_label = tasks.of_entry(data).support or "support"
    conditions = list(dict.fromkeys(c for row in means.values() for c in row))
    if not conditions:
        return []
    ranked = [n for n in means if n not in own]
    marked = len(ranked) > 1
    best = {c: max((means[n][c] for n in ranked if _finite(means[n].get(c))), default=None) for c in conditions}
    order = ranked + [n for n in means if n in own]
    label = max(len(title), *(len(n) + (len(REFERENCE_TAG) if n in own else 0) for n in means)) + 2
    cols = [max(width, len(c) + 1) for c in conditions]
    label = max(label, len(support_label) + 4)
    lines = [title.ljust(label) + "".join(c.rjust(w) for c, w in zip(conditions, cols))]
    if support:  # the evidence under each column: one count where every row rests on the same, else the range
        cells = []
        for c, w in zip(conditions, cols):
            counts = sorted({int(s[c]) for s in support.values() if c in s})
            text = "-" if not counts else str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
            cells.append((text + " ").rjust(w))
        lines.append(f"({support_label})".ljust(label) + "".join(cells))
    for name in order:
        row = means[name]
        cells = []
        for c, w in zip(conditions, cols):
            v = row.get(c)
            star = marked and name not in own and v == best[c]
            text = "-" if not _finite(v) else f"{v:.3f}" + ("*" if star else " ")
            cells.append(text.rjust(w))
        lines.append((name + (REFERENCE_TAG if name in own else "")).ljust(label) + "".join(cells))
    source = f"{', '.join(sorted(teachers))}'s pseudo-labels" + (f" on {reference}" if reference else "")
    notes = []
    if marked:
        notes.append("* best per condition" + (" among the other models" if own else ""))
    if own:
        notes.append("the reference grades its own pseudo-labels: not ranked")
    lines.append(f"(against {source}" + "".join(f"; {n}" for n in notes) + ")")
    return lines


def _finite(v: object) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def unpredictable_lines(evaluations: dict[str, str]) -> list[str]:
    """One line per evaluation whose model cannot predict some Cityscapes classes (summary.json's
    `unpredictable_classes`, `label_space`): `<model>: cannot predict <classes> (label space <space>): their xi
    and IoU are NaN`; [] when every model can predict every class."""
    lines = []
    for name, path in evaluations.items():
        summary = Path(path) / SUMMARY
        if not summary.is_file():
            continue
        data = json.loads(summary.read_text())
        classes = data.get("unpredictable_classes") or []
        if classes:
            lines.append(f"{name}: cannot predict {', '.join(classes)} (label space {data.get('label_space')}): "
                         "their xi and IoU are NaN")
    return lines
