"""The table a run ends with: mean xi per model x adverse condition, read back from each evaluation's
`summary.json` (a cached rerun reads JSON, no torch), the best model of each condition marked, as
evaluation harnesses print their leaderboards."""
from __future__ import annotations

import json
import math
from pathlib import Path


def xi_lines(evaluations: dict[str, str], reference: str | None = None, width: int = 9) -> list[str]:
    """Rows `model  value value ...`, one column per adverse condition (short names: Day-RAIN, ...),
    the column's best marked `*`; [] when no evaluation has a summary."""
    means: dict[str, dict[str, float]] = {}
    teachers: set[str] = set()
    for name, path in evaluations.items():
        summary = Path(path) / "summary.json"
        if summary.is_file():
            data = json.loads(summary.read_text())
            teachers.add(str(data.get("reference_model")))
            means[name] = {c: v for c, v in (data.get("xi_mean") or {}).items() if c != reference}
    conditions = list(dict.fromkeys(c for row in means.values() for c in row))
    if not conditions:
        return []
    best = {c: max((row[c] for row in means.values() if _finite(row.get(c))), default=None) for c in conditions}
    label = max(len("mean xi"), *(len(n) for n in means)) + 2
    cols = [max(width, len(c) + 1) for c in conditions]
    lines = ["mean xi".ljust(label) + "".join(c.rjust(w) for c, w in zip(conditions, cols))]
    for name, row in means.items():
        cells = []
        for c, w in zip(conditions, cols):
            v = row.get(c)
            text = "-" if not _finite(v) else f"{v:.3f}" + ("*" if len(means) > 1 and v == best[c] else " ")
            cells.append(text.rjust(w))
        lines.append(name.ljust(label) + "".join(cells))
    source = f"{', '.join(sorted(teachers))}'s pseudo-labels" + (f" on {reference}" if reference else "")
    lines.append(f"(against {source}" + ("; * best per condition)" if len(means) > 1 else ")"))
    return lines


def _finite(v: object) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)
