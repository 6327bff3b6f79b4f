"""A toy third task, declared outside the package (tests/test_task_plugin.py): which Cityscapes classes an image shows
(per-image class presence: at least MIN_PIXELS pixels of the class), from a segmenter's label map. Its pseudo-labels
are the reference's presence on the clean image; its evaluation scores every condition's presence against them
(recall: the share of the reference's classes still found, shown as the run's table) and against the renderer's
labels (accuracy over the 19 classes). It supplies only the work of the task-neutral stages (pairedgta.work)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.datasets import load_image, load_label
from pairedgta.entries import StageResult, model_hash_config
from pairedgta.models import shared_model

MIN_PIXELS = 16


def presence(label_map: np.ndarray) -> np.ndarray:
    label_map = np.asarray(label_map)
    counts = np.bincount(label_map[label_map < NUM_CLASSES].ravel().astype(np.int64), minlength=NUM_CLASSES)
    return counts >= MIN_PIXELS


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, sort_keys=True))
    tmp.replace(path)


class PresenceLabels(StageResult):
    def presence(self) -> dict[str, list[bool]]:
        return json.loads((self.path / "presence.json").read_text())["groups"]

    def reference_model(self) -> str:
        return str(self.manifest()["config"]["reference_model"]["name"])

    def artifacts(self) -> list[Path]:
        return [self.path / "presence.json"]


@dataclass(frozen=True)
class PresencePseudolabels:
    task: Any
    result_cls: type[PresenceLabels] = PresenceLabels

    def version(self, model_cfg: dict[str, Any]) -> str:
        return "1"

    def hash_config(self, ctx: Any, dataset: Any, model_cfg: dict[str, Any]) -> dict[str, Any]:
        return {"task": self.task.name, "reference_model": model_hash_config(model_cfg), "reference": dataset.reference,
                "min_pixels": MIN_PIXELS}

    def compute(self, ctx: Any, dataset: Any, out: Path, model_cfg: dict[str, Any]) -> dict[str, Any]:
        model = shared_model(model_cfg, device=ctx.run.device)
        groups = {}
        for g in dataset.groups:
            labels, _ = model.predict(load_image(g.images[dataset.reference])[None])
            groups[g.group_id] = presence(labels[0].numpy()).tolist()
        _write_json(out / "presence.json", {"reference_model": model_cfg["name"], "groups": groups})
        return {"groups": len(groups)}


class PresenceEvaluation(StageResult):
    @property
    def model(self) -> str:
        return str(self.summary()["model"])

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / "summary.json").read_text())

    def xi(self) -> pd.DataFrame:
        return pd.read_csv(self.path / "presence.csv")

    def metrics(self, per_class: bool = False, headline: str | None = None) -> dict[str, float]:
        s = self.summary()
        return {**{f"presence_recall/{c}": v for c, v in s["xi_mean"].items()},
                **{f"presence_accuracy/{c}": v for c, v in s["accuracy"].items()}}

    def artifacts(self) -> list[Path]:
        return [self.path / "presence.csv", self.path / "summary.json"]


@dataclass(frozen=True)
class PresenceEvaluate:
    task: Any
    result_cls: type[PresenceEvaluation] = PresenceEvaluation

    def version(self, model_cfg: dict[str, Any]) -> str:
        return "1"

    def settings(self, ctx: Any, dataset: Any) -> dict[str, Any]:
        return {"min_pixels": MIN_PIXELS, "clean": dataset.reference}

    def hash_config(self, model_cfg: dict[str, Any], settings: dict[str, Any], conditions: list[str],
                    threads: int) -> dict[str, Any]:
        return {"task": self.task.name, "model": model_hash_config(model_cfg), "metric": settings,
                "conditions": conditions, "threads": threads}

    def groups(self, ctx: Any, dataset: Any, pseudo: Any, model_cfg: dict[str, Any], conditions: list[str],
               groups: list[Any], settings: dict[str, Any]) -> list[dict[str, Any]]:
        model = shared_model(model_cfg, device=ctx.run.device)
        out = []
        for g in groups:
            per = {}
            for c in conditions:
                if c not in g.images:
                    continue
                labels, _ = model.predict(load_image(g.images[c])[None])
                truth = presence(load_label(g.labels[c])).tolist() if c in g.labels else None
                per[c] = {"predicted": presence(labels[0].numpy()).tolist(), "truth": truth}
            out.append({"group_id": g.group_id, "conditions": per})
        return out

    def read_parts(self, parts: Path) -> dict[str, dict[str, Any]]:
        found: dict[str, dict[str, Any]] = {}
        for path in sorted(parts.glob("part-*.json")) if parts.is_dir() else []:
            found.update({r["group_id"]: r for r in json.loads(path.read_text())})
        return found

    def write_part(self, parts: Path, shard: int, num: int, results: list[dict[str, Any]]) -> None:
        parts.mkdir(parents=True, exist_ok=True)
        _write_json(parts / f"part-{shard:05d}-of-{num:05d}.json", results)

    def compute(self, ctx: Any, dataset: Any, dataset_key: str, pseudo: PresenceLabels, model_cfg: dict[str, Any],
                conditions: list[str], settings: dict[str, Any], out: Path, parts: Path) -> dict[str, Any]:
        done = self.read_parts(parts)
        missing = [g for g in dataset.groups if g.group_id not in done]
        for r in self.groups(ctx, dataset, pseudo, model_cfg, conditions, missing, settings):
            done[r["group_id"]] = r
        reference = pseudo.presence()
        rows, recall, accuracy = [], {}, {}
        for c in conditions:
            found = kept = right = scored = 0
            for g in dataset.groups:
                r = done[g.group_id]["conditions"].get(c)
                if r is None:
                    continue
                pred, ref = np.array(r["predicted"]), np.array(reference[g.group_id])
                found, kept = found + int(ref.sum()), kept + int((pred & ref).sum())
                if r["truth"] is not None:
                    right, scored = right + int((pred == np.array(r["truth"])).sum()), scored + NUM_CLASSES
            recall[c] = kept / found if found else float("nan")
            accuracy[c] = right / scored if scored else float("nan")
            rows.append({"model": model_cfg["name"], "reference_model": pseudo.reference_model(), "condition": c,
                         "class_name": "mean", "xi": recall[c], "accuracy": accuracy[c], "reference_classes": found})
        tmp = out / ".presence.csv.tmp"
        pd.DataFrame(rows).to_csv(tmp, index=False)
        tmp.replace(out / "presence.csv")
        _write_json(out / "summary.json", {"task": self.task.name, "model": model_cfg["name"],
                                           "reference_model": pseudo.reference_model(), "xi_mean": recall,
                                           "accuracy": accuracy, "groups": len(done)})
        return {"groups": len(done)}

    def said(self, result: Any, model_cfg: dict[str, Any]) -> None:
        return None

    def record(self, ctx: Any, result: Any, model_cfg: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str],
                                                                               dict[str, Any]]:
        return {"min_pixels": MIN_PIXELS}, {"task": self.task.name}, {"presence_table.json": result.xi()}
