"""Label spaces: a model's output classes mapped onto the 19 Cityscapes train classes the metrics use.

Every model source goes through one `LabelMap` (pairedgta/models/contract.py): several source classes that mean one
Cityscapes class add their probabilities; a class with no Cityscapes counterpart leaves the distribution, which is
renormalised over what is left; a Cityscapes class no source class maps to is one the model *cannot* predict, reported
as such (its xi and IoU are NaN with that reason, never a silent 0). The shipped tables are in pairedgta/data/labels/;
a user's own is a TSV of `source class <TAB> Cityscapes class` (or `-`), one row per output channel, in order.
Torch is imported only to apply a map."""
from __future__ import annotations

import csv
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import ConfigError, ModelError
from pairedgta.lazy import lazy_module

torch = lazy_module("torch")
log = logging.getLogger("pairedgta.models")

TABLES = Path(__file__).resolve().parents[1] / "data" / "labels"
# model.labels= names of the shipped label spaces (cityscapes: the metrics' own, no table)
SHIPPED = ("cityscapes", "mapillary_vistas_v1.2", "ade20k", "coco_panoptic")
NONE = ("-", "", "none", "void", "ignore")  # "no Cityscapes counterpart" in a table's target column


def normalise_name(name: str) -> str:
    """'Traffic_Light', 'traffic-light' and 'traffic light' are one name: checkpoints spell them all ways."""
    return re.sub(r"[\s_\-]+", " ", str(name).strip().lower())


_CITYSCAPES = {normalise_name(n): i for i, n in enumerate(CLASS_NAMES)}
_GENERIC = re.compile(r"^label ?\d+$")  # transformers' placeholder id2label (LABEL_0, ...): says nothing


@dataclass(frozen=True)
class LabelMap:
    """Per output channel, the Cityscapes train id it contributes to (-1: none)."""

    space: str                      # what the user named: a shipped space or the TSV's path
    source_classes: tuple[str, ...]
    target: tuple[int, ...]

    @property
    def num_outputs(self) -> int:
        return len(self.target)

    @property
    def identity(self) -> bool:
        return self.target == tuple(range(NUM_CLASSES))

    @property
    def unpredictable(self) -> tuple[str, ...]:
        """The Cityscapes classes no output channel maps to: the model cannot predict them."""
        reached = set(self.target)
        return tuple(n for i, n in enumerate(CLASS_NAMES) if i not in reached)

    @property
    def dropped(self) -> tuple[str, ...]:
        """The source classes without a Cityscapes counterpart (their probability leaves the distribution)."""
        return tuple(c for c, t in zip(self.source_classes, self.target) if t < 0)

    def describe(self) -> str:
        many = sum(1 for t in range(NUM_CLASSES) if self.target.count(t) > 1)
        parts = [f"{self.num_outputs} classes of {self.space}"]
        if many:
            parts.append(f"{many} Cityscapes classes gather several")
        if self.dropped:
            parts.append(f"{len(self.dropped)} without a Cityscapes counterpart leave the distribution")
        if self.unpredictable:
            parts.append(f"cannot predict: {', '.join(self.unpredictable)}")
        return "; ".join(parts)

    def apply(self, probs: "torch.Tensor") -> "torch.Tensor":
        """B x num_outputs x H x W probabilities -> B x 19 x H x W: mapped classes add up, the rest is renormalised."""
        if self.identity:
            return probs
        index = torch.tensor([max(t, 0) for t in self.target], device=probs.device)
        keep = torch.tensor([t >= 0 for t in self.target], device=probs.device, dtype=probs.dtype).view(1, -1, 1, 1)
        out = probs.new_zeros((probs.shape[0], NUM_CLASSES, *probs.shape[2:]))
        out.index_add_(1, index, probs * keep)
        if self.dropped:
            out = out / out.sum(dim=1, keepdim=True).clamp_min(1e-12)
        return out

    def without_last(self) -> "LabelMap":
        return LabelMap(self.space, self.source_classes[:-1], self.target[:-1])


def _target_of(name: str, where: str) -> int:
    if name.strip().lower() in NONE:
        return -1
    index = _CITYSCAPES.get(normalise_name(name))
    if index is None:
        raise ConfigError(f"{where}: '{name}' is not a Cityscapes class; use one of {', '.join(CLASS_NAMES)} "
                          "or - for a class without a counterpart")
    return index


def read_table(path: Path, space: str | None = None) -> LabelMap:
    """A label TSV: comment lines `#`; rows `source_class<TAB>cityscapes_class`, or with a header naming the columns
    `source_class` and `cityscapes_class` (the shipped tables also give `index` and `follows`), one per channel."""
    space = space or str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"model.labels={space}: no such file; give a shipped label space "
                          f"({', '.join(SHIPPED)}) or a TSV of 'source class<TAB>Cityscapes class'") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"model.labels={space}: cannot read it ({exc}); it must be a UTF-8 TSV of "
                          "'source class<TAB>Cityscapes class'") from None
    rows = [(n, r) for n, r in enumerate(csv.reader(text.splitlines(), delimiter="\t"), 1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    src, dst = 0, 1
    if rows and {"source_class", "cityscapes_class"} <= {c.strip() for c in rows[0][1]}:
        header = [c.strip() for c in rows[0][1]]
        src, dst = header.index("source_class"), header.index("cityscapes_class")
        rows = rows[1:]
    if not rows:
        raise ConfigError(f"model.labels={space}: the table has no rows; one row per output channel: "
                          "'source class<TAB>Cityscapes class'")
    names, target = [], []
    for line, row in rows:
        if len(row) <= max(src, dst):
            raise ConfigError(f"model.labels={space} line {line}: expected 'source class<TAB>Cityscapes class', "
                              f"got {chr(9).join(row)!r}")
        names.append(row[src].strip())
        target.append(_target_of(row[dst], f"model.labels={space} line {line}"))
    return LabelMap(space, tuple(names), tuple(target))


def _cityscapes(id2label: Mapping[int, str] | None, where: str) -> LabelMap:
    names = [id2label[i] for i in sorted(id2label)] if id2label else None
    if names and not all(_GENERIC.match(normalise_name(n)) for n in names):
        known = [_CITYSCAPES.get(normalise_name(n)) for n in names]
        if len(names) == NUM_CLASSES and None not in known and len(set(known)) == NUM_CLASSES:
            return LabelMap("cityscapes", tuple(names), tuple(known))  # matched by name: any channel order
        unknown = [n for n, k in zip(names, known) if k is None]
        if len(names) != NUM_CLASSES:  # another count: the label space to name, not which names differ
            which, advice = "", _guess(len(names)).lstrip("; ")
        else:
            which = (f": {', '.join(unknown[:3])}{', ...' if len(unknown) > 3 else ''} "
                     f"{'is no Cityscapes class' if len(unknown) == 1 else 'are no Cityscapes classes'}" if unknown
                     else ": some names repeat")
            advice = (f"set model.labels= to its label space ({', '.join(SHIPPED[1:])}) or to a TSV mapping its "
                      "classes to Cityscapes")
        # the example of the Cityscapes classes is theirs (the checkpoint's names are given as its own, first)
        raise ModelError(f"{where}: the checkpoint's {len(names)} classes ({', '.join(names[:5])}, ...) are not the 19 "
                         f"Cityscapes classes ({', '.join(CLASS_NAMES[:5])}, ...){which}; {advice}")
    return LabelMap("cityscapes", CLASS_NAMES, tuple(range(NUM_CLASSES)))


def resolve_labels(spec: Any, *, id2label: Mapping[int, str] | None = None, where: str = "model") -> LabelMap:
    """`model.labels` as a LabelMap. `cityscapes` uses the checkpoint's own class names (`id2label`) when it has real
    ones, matched by name; a shipped space or a TSV gives its rows in channel order."""
    spec = "cityscapes" if spec is None else str(spec)
    if spec == "cityscapes":
        return _cityscapes(id2label, where)
    if spec in SHIPPED:
        return against_checkpoint(read_table(TABLES / f"{spec}.tsv", spec), id2label, where)
    if "/" in spec or spec.endswith((".tsv", ".txt")):
        return against_checkpoint(read_table(Path(spec).expanduser()), id2label, where)
    raise ConfigError(f"model.labels={spec!r} is unknown; choose one of {', '.join(SHIPPED)} or a path to a TSV of "
                      "'source class<TAB>Cityscapes class'")


def against_checkpoint(table: LabelMap, id2label: Mapping[int, str] | None, where: str) -> LabelMap:
    """A table read against the checkpoint's own class names: the same names in another channel order are reordered
    (a checkpoint need not list its classes as the dataset does); names that differ (a synonym, a typo) are logged,
    and the table's order is kept. Placeholder names (LABEL_0, ...) say nothing."""
    names = [str(id2label[i]) for i in sorted(id2label)] if id2label else []
    if not names or all(_GENERIC.match(normalise_name(n)) for n in names):
        return table
    rows = table.source_classes if len(names) == table.num_outputs else table.source_classes[:len(names)]
    if [normalise_name(n) for n in names] == [normalise_name(r) for r in rows]:
        return table
    by_name = {normalise_name(c): t for c, t in zip(table.source_classes, table.target)}
    if len(set(map(normalise_name, names))) == len(names) and all(normalise_name(n) in by_name for n in names):
        log.info("%s: the checkpoint lists the classes of %s in another order; matched by name", where, table.space)
        return LabelMap(table.space, tuple(names), tuple(by_name[normalise_name(n)] for n in names))
    differ = [f"{i}: {n!r} vs {r!r}" for i, (n, r) in enumerate(zip(names, rows)) if normalise_name(n) != normalise_name(r)]
    log.warning("%s: %d of the checkpoint's class names differ from model.labels=%s (%s); the table's channel order is "
                "used: check that it is the checkpoint's", where, len(differ), table.space, "; ".join(differ[:3]))
    return table


def fit_outputs(labels: LabelMap, channels: int, where: str) -> LabelMap:
    """The map for a model with `channels` outputs: equal to the table, or Vistas' 65-class head (no Unlabeled)."""
    if channels == labels.num_outputs:
        return labels
    if labels.space == "mapillary_vistas_v1.2" and channels == labels.num_outputs - 1:
        return labels.without_last()  # the 65 evaluated classes, as most Vistas heads are trained
    hint = _guess(channels)
    raise ModelError(f"{where}: the model outputs {channels} channels, but model.labels={labels.space} has "
                     f"{labels.num_outputs} classes{hint}")


def _guess(channels: int) -> str:
    sizes = {19: "cityscapes", 66: "mapillary_vistas_v1.2", 65: "mapillary_vistas_v1.2", 150: "ade20k",
             133: "coco_panoptic"}
    if channels in sizes:
        space = sizes[channels]
        return f"; is it a{'n' if space[0] in 'aeiou' else ''} {space} model? set model.labels={space}"
    return "; set model.labels= to its label space or to a TSV with one row per output channel"


__all__ = ["LabelMap", "resolve_labels", "read_table", "fit_outputs", "normalise_name", "SHIPPED"]
