"""rho_valid^c, eq. (valid_spearman): Spearman correlation of clean vs adverse prediction mass over the
frames that matter for class c — the top-M by clean count (the paper), or every frame with a
non-zero clean count (a selection that does not depend on M)."""
from __future__ import annotations

import math

import numpy as np

SELECTIONS = ("top_m", "nonzero")


def select_frames(clean_counts, m: int = 25, selection: str = "top_m") -> np.ndarray:
    """Indices of D_valid. top_m: the M frames with the most clean pixels of the class, among the frames that
    show it at all: where fewer than M do, padding with frames of count 0 would add ties that say nothing
    about the class (3 informative frames in reversed order once gave 0.99); the row's n_frames says how
    many there were. Ties at the top-M boundary break by frame order, so the set is deterministic."""
    clean = np.asarray(clean_counts, dtype=float)
    if selection == "top_m":
        if m < 1:
            raise ValueError(f"m must be >= 1, got {m}")
        present = np.flatnonzero(clean > 0)
        order = present[np.argsort(-clean[present], kind="stable")]
        return np.sort(order[:m])
    if selection == "nonzero":
        return np.flatnonzero(clean > 0)
    raise ValueError(f"unknown selection {selection!r}; use one of {SELECTIONS}")


def spearman(x, y) -> float:
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 2 or np.all(x == x[0]) or np.all(y == y[0]):
        return math.nan  # the rank correlation is undefined for constant input
    from scipy.stats import spearmanr  # scipy.stats costs ~0.5 s to import: only where a rho is computed

    return float(spearmanr(x, y).statistic)


def rho_valid(clean_counts, adverse_counts, m: int = 25, selection: str = "top_m") -> float:
    clean = np.asarray(clean_counts, dtype=float)
    adverse = np.asarray(adverse_counts, dtype=float)
    if clean.shape != adverse.shape:
        raise ValueError(f"clean and adverse counts differ in length: {clean.shape} vs {adverse.shape}")
    idx = select_frames(clean, m, selection)
    return spearman(clean[idx], adverse[idx])


def rho_rows(clean_counts, adverse_counts, selections, m: int = 25, resamples: int = 1000, confidence: float = 0.95,
             seed: int = 0, headline: str | None = None, min_frames: int = 0) -> list[dict]:
    """One row per selection: rho_valid over its frames with a percentile bootstrap interval over those
    frames (`m` is recorded for top_m only). Shared by evaluate and the authors' per-frame counts.
    `headline` is true for the headline selection only over at least `min_frames` frames: a Spearman of 2
    or 3 frames is +-1 by chance, so such a value stays in the row, with its n_frames, but is no headline."""
    from pairedgta.metrics.bootstrap import drop_zero_width, spearman_ci

    clean = np.asarray(clean_counts, dtype=float)
    adverse = np.asarray(adverse_counts, dtype=float)
    rows = []
    for sel in selections:
        idx = select_frames(clean, m, sel)
        x, y = clean[idx], adverse[idx]
        lo, hi = drop_zero_width(*spearman_ci(x, y, resamples, confidence, seed))
        rows.append({"selection": sel, "m": m if sel == "top_m" else math.nan, "n_frames": len(idx),
                     "rho": spearman(x, y), "ci_low": lo, "ci_high": hi,
                     "headline": sel == headline and len(idx) >= min_frames, "min_frames": int(min_frames)})
    return rows
