"""Strict JSON for everything the project writes: NaN and +-inf become null, numpy scalars and arrays
become plain numbers and lists, and ``allow_nan=False`` proves no bare NaN reaches a file (strict
parsers such as jq, JavaScript or ``json.load(parse_constant=...)`` reject it). Beside it the atomic writes of
bytes and of numpy's ``.npz`` archives (`write_bytes`, `write_npz`), which every stage's ``.npz`` goes through."""
from __future__ import annotations

import io
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


def write_bytes(path: str | os.PathLike, data: bytes | memoryview) -> None:
    """`data` under a temporary name beside `path`, renamed into place: never half-written, and the file is
    closed and the temporary removed on any error (a full disk) before the error goes on."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_npz(path: str | os.PathLike, arrays: dict[str, Any], compress: bool = True) -> None:
    """`np.savez_compressed(path, **arrays)` (or `np.savez`), the same bytes, written by `write_bytes`. The
    archive is built in memory first: numpy 1.x's savez leaves its ZipFile open when a write fails, and the
    garbage collector closing it later on the closed file printed ``Exception ignored in: ZipFile.__del__ ...
    ValueError: seek of closed file`` after a full disk's one-line error. In memory no write can fail, and
    the one write that can is a plain file's, closed by its `with`."""
    import numpy as np

    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays)
    with buf.getbuffer() as view:
        write_bytes(path, view)
