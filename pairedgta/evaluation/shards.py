"""Partial sums of shard jobs (evaluate.shard i of evaluate.num_shards): each job stores its groups'
counts, and the unsharded run merges them instead of counting those groups again."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from pairedgta.jsonio import write_bytes, write_npz

log = logging.getLogger("pairedgta.evaluate")


def read_parts(parts: Path) -> dict[str, dict[str, Any]]:
    """The groups' counts the shard jobs stored in `parts`, by group id; an unreadable part is skipped
    (its groups are counted again)."""
    found: dict[str, dict[str, Any]] = {}
    for path in sorted(parts.glob("part-*.json")) if parts.is_dir() else []:
        try:
            rows = json.loads(path.read_text())
            with np.load(path.with_suffix(".npz"), allow_pickle=False) as maps:
                for i, r in enumerate(rows):
                    present = r.pop("pred_conditions")
                    r["pred"] = {c: maps[f"{i}|{c}"] for c in present}
                    r["conf"] = {c: maps[f"c{i}|{c}"] for c in present if f"c{i}|{c}" in maps.files}
            for r in rows:
                found[r["group_id"]] = r
        except (OSError, ValueError, json.JSONDecodeError, KeyError, TypeError):
            log.warning("evaluate: ignoring unreadable shard result %s (its groups are computed again)", path)
    return found


def write_part(parts: Path, shard: int, num: int, results: list[dict[str, Any]]) -> Path:
    """The shard's sums as JSON and its label maps beside it (`.npz`); the maps are written first, so a
    JSON file is only ever seen with its maps complete."""
    parts.mkdir(parents=True, exist_ok=True)
    path = parts / f"part-{shard:05d}-of-{num:05d}.json"
    maps = {f"{i}|{c}": m for i, r in enumerate(results) for c, m in (r.get("pred") or {}).items()}
    maps.update({f"c{i}|{c}": m for i, r in enumerate(results) for c, m in (r.get("conf") or {}).items()})
    rows = [{**{k: v for k, v in r.items() if k not in ("pred", "conf")}, "pred_conditions": list(r.get("pred") or {})}
            for r in results]
    write_npz(path.with_suffix(".npz"), maps)  # atomic; a failed write leaves neither temporary nor open ZipFile
    write_bytes(path, json.dumps(rows, default=_jsonable, allow_nan=False).encode())
    return path


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
