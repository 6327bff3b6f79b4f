"""Strict JSON for everything the project writes: NaN and +-inf become null, numpy scalars and arrays
become plain numbers and lists, and ``allow_nan=False`` proves no bare NaN reaches a file (strict
parsers such as jq, JavaScript or ``json.load(parse_constant=...)`` reject it)."""
from __future__ import annotations

import json
import math
import os
import uuid
from pathlib import Path
from typing import Any


def strict(obj: Any) -> Any:
    """`obj` with every non-finite float replaced by None and numpy/Path values made plain."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, (str, int, float, bool)) else k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if hasattr(obj, "tolist") and hasattr(obj, "dtype"):  # numpy scalar or array, torch scalar
        return strict(obj.tolist())
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    try:
        return strict(float(obj))
    except (TypeError, ValueError):
        return str(obj)


def dumps(obj: Any, **kwargs: Any) -> str:
    return json.dumps(strict(obj), allow_nan=False, **kwargs)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2, **kwargs: Any) -> None:
    """Write strict JSON under a temporary name and rename it into place (never half-written)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_text(dumps(obj, indent=indent, **kwargs) + "\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
