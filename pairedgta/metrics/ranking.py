"""rho_valid^c, eq. (valid_spearman): Spearman correlation of clean vs adverse prediction mass over the
frames that matter for class c — the top-M by clean count (the paper), or every frame with a
non-zero clean count (a selection that does not depend on M)."""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import spearmanr

SELECTIONS = ("top_m", "nonzero")


def select_frames(clean_counts, m: int = 25, selection: str = "top_m") -> np.ndarray:
    """Indices of D_valid. Ties at the top-M boundary break by frame order, so the set is deterministic."""
    clean = np.asarray(clean_counts, dtype=float)
    if selection == "top_m":
        if m < 1:
            raise ValueError(f"m must be >= 1, got {m}")
        order = np.argsort(-clean, kind="stable")
        return np.sort(order[: min(m, len(clean))])
    if selection == "nonzero":
        return np.flatnonzero(clean > 0)
    raise ValueError(f"unknown selection {selection!r}; use one of {SELECTIONS}")


def spearman(x, y) -> float:
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 2 or np.all(x == x[0]) or np.all(y == y[0]):
        return math.nan  # the rank correlation is undefined for constant input
    return float(spearmanr(x, y).statistic)


def rho_valid(clean_counts, adverse_counts, m: int = 25, selection: str = "top_m") -> float:
    clean = np.asarray(clean_counts, dtype=float)
    adverse = np.asarray(adverse_counts, dtype=float)
    if clean.shape != adverse.shape:
        raise ValueError(f"clean and adverse counts differ in length: {clean.shape} vs {adverse.shape}")
    idx = select_frames(clean, m, selection)
    return spearman(clean[idx], adverse[idx])
