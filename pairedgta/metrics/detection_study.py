"""Is detection xi the best label-free judge of a detector's robustness? (+experiment=metric_validity task=detection,
figure `det_estimators`.) Segmentation's study (pairedgta/metrics/estimator_study.py) asked it of xi; this asks it of
detection xi among the label-free estimators the detection field has, against the renderer's ground truth.

Per (ranked detector, adverse condition) cell, from one evaluation of every detector (its stored detections, its
per-group counts and, with detection.estimators, two more forwards an image):

  det_xi             mean detection xi against the reference's confident clean boxes (label-free)
  det_precision      the share of its confident boxes that match a reference box (xi's precision side)
  det_xi_f           the harmonic mean of the two (0 where nothing is found: a recall of 0)
  pseudo_ap50        AP50 of its detections with the reference's clean boxes as ground truth
  relative_det_xi    det_xi under the condition / on the clean image
  ac                 average confidence: the mean score of its boxes scored >= 0.05 (Hendrycks & Gimpel's AC)
  relative_ac        ac under the condition / on the clean image
  atc                ATC-style (Garg et al. 2022): t is fitted on the clean images so that as many boxes score >= t as
                     match a true object there (uses the clean ground truth); the count of boxes >= t under the
                     condition / on the clean image
  self_agreement     F1 of its confident boxes under the condition against its own on the clean image (IoU >= 0.5)
  committee          mean F1 of its confident boxes with each other ranked detector's, same image
  bos, relative_bos  box stability under feature dropout (BoS, ICLR 2024; pairedgta/metrics/box_stability.py)
  pcr                pre-NMS candidate consistency (PCR-style, ICCV 2025)
  clean_ap           the clean COCO AP alone (uses the clean ground truth)

Targets: COCO AP under the condition, and rPC = AP(condition) / AP(clean). The statistics are segmentation's:
within each adverse condition Spearman (and Kendall) across the ranked detectors, their mean over conditions with a
BCa interval over scenes and detectors drawn together (the same draws for every estimator, so differences are
paired), the difference to det_xi with Holm's adjustment over the estimators, the joint-null permutation p; the
pooled correlation beside it. Every estimator and target is recomputed on each draw of scenes from per-image sums
(AP through coco_resample, pycocotools' per-image matching re-accumulated with image weights); ATC's threshold is
kept at its whole-data value."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from pairedgta.metrics import coco_resample
from pairedgta.metrics.detection_xi import match as match_boxes

ESTIMATORS = ("det_xi", "det_precision", "det_xi_f", "pseudo_ap50", "relative_det_xi", "ac", "relative_ac", "atc",
              "self_agreement", "committee", "bos", "relative_bos", "pcr", "clean_ap")
USES_CLEAN_LABELS = ("atc", "clean_ap")
TARGETS = ("rpc", "ap")
NEEDS_FORWARDS = ("bos", "relative_bos", "pcr")  # detection.estimators
AC_FLOOR = 0.05
RPC_MIN_CLEAN_AP = 0.05  # as pairedgta/metrics/corruption.py: rPC is undefined below this clean AP
MIN_RANKED = 4
STAT_COLUMNS = ("estimator", "target", "scope", "n_models", "n_conditions", "n_groups", "spearman", "spearman_ci_low",
                "spearman_ci_high", "kendall", "kendall_ci_low", "kendall_ci_high", "p_permutation",
                "p_permutation_holm", "permutations", "spearman_minus_xi", "spearman_minus_xi_ci_low",
                "spearman_minus_xi_ci_high", "p_minus_xi", "p_minus_xi_holm", "mae", "mae_ci_low", "mae_ci_high",
                "mae_baseline", "uses_clean_labels", "resamples", "confidence")


@dataclass
class Detector:
    """One detector's evaluation as the study reads it; images are in the dataset's group order (COCO ids 1..N)."""

    model: str
    threshold: float
    detections: dict[str, list[dict[str, Any]]]  # condition -> COCO results
    found: dict[str, np.ndarray]  # condition -> N x K (the reference's boxes it finds)
    refs: dict[str, np.ndarray]  # condition -> N x K
    supported: dict[str, np.ndarray]  # condition -> K bools (xi's support rule on the whole data)
    matched: dict[str, np.ndarray]  # condition -> N (its confident boxes matching a reference box)
    confident: dict[str, np.ndarray]  # condition -> N
    bos: dict[str, np.ndarray] = field(default_factory=dict)  # condition -> N (NaN: no box / not reachable)
    pcr: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Study:
    """What every weighting of the scenes recomputes from (`values`)."""

    models: list[str]
    conditions: list[str]
    clean: str
    n: int
    sums: dict[str, np.ndarray]  # name -> M x C x N per-image terms (see `_terms`)
    ap: list[list[coco_resample.PerImage]]  # M x C: against the ground truth
    pseudo: list[list[coco_resample.PerImage]]  # M x C: against the reference's clean boxes
    committee_pairs: np.ndarray  # M x M x C x N matches between two detectors' confident boxes
    atc_threshold: np.ndarray  # M
    reachable: dict[str, bool]  # estimator -> computed for every model


def _by_image(results: list[dict[str, Any]], n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    out: list[list] = [[[], [], []] for _ in range(n)]
    for r in results:
        i = int(r["image_id"]) - 1
        if 0 <= i < n:
            x, y, w, h = r["bbox"]
            out[i][0].append((x, y, x + w, y + h))
            out[i][1].append(r["score"])
            out[i][2].append(int(r["category_id"]) - 1)
    return [(np.asarray(b, float).reshape(-1, 4), np.asarray(s, float), np.asarray(c, np.int64)) for b, s, c in out]


def _matches(a: tuple, b: tuple, threshold_a: float, threshold_b: float, iou: float) -> tuple[int, int, int]:
    """(matched pairs, |A|, |B|) of two images' confident boxes, one to one, same class."""
    ka, kb = a[1] >= threshold_a, b[1] >= threshold_b
    ba, la = a[0][ka], a[2][ka]
    bb, sb, lb = b[0][kb], b[1][kb], b[2][kb]
    found, _ = match_boxes(ba, la, bb, sb, lb, iou)
    return int(found.sum()), int(ka.sum()), int(kb.sum())


def _atc_threshold(ap_clean: coco_resample.PerImage, results: list[dict[str, Any]]) -> float:
    """The score t at which as many boxes score >= t as match a true object (IoU 0.5) among all of them."""
    tp = sum(float(t[0].sum()) for t in ap_clean.tp)
    scores = np.sort(np.asarray([r["score"] for r in results], float))[::-1]
    if not len(scores):
        return math.nan
    k = int(round(tp))
    return float(scores[min(max(k, 1), len(scores)) - 1]) if k > 0 else float(scores[0] + 1e-9)


def prepare(detectors: Sequence[Detector], ground_truth: dict[str, dict[str, Any]], pseudo_gt: dict[str, Any],
            conditions: Sequence[str], clean: str, n: int, iou: float = 0.5, max_detections: int = 100) -> Study:
    """Per-image sums of every estimator and the per-image matches of both APs, once."""
    m_count, conds = len(detectors), list(conditions)
    c_count = len(conds)
    per_image = [[_by_image(d.detections.get(c, []), n) for c in conds] for d in detectors]
    sums: dict[str, np.ndarray] = {k: np.zeros((m_count, c_count, n)) for k in (
        "ac_sum", "ac_n", "atc_n", "self_m", "self_clean", "self_adv", "matched", "confident", "bos", "bos_ok", "pcr",
        "pcr_ok")}
    xi_found, xi_refs = [], []
    ap, pseudo, thresholds = [], [], np.full(m_count, np.nan)
    c0 = conds.index(clean)
    n_classes = max((r.shape[1] for d in detectors for r in d.refs.values()), default=1)
    for j, d in enumerate(detectors):
        ap.append([coco_resample.match(ground_truth[c], d.detections.get(c, []), max_detections)
                   if c in ground_truth else None for c in conds])
        pseudo.append([coco_resample.match(pseudo_gt, d.detections.get(c, []), max_detections, iou_thrs=[0.5])
                       for c in conds])
        if ap[j][c0] is not None:
            thresholds[j] = _atc_threshold(coco_resample.match(ground_truth[clean], d.detections.get(clean, []),
                                                               max_detections, iou_thrs=[0.5]),
                                           d.detections.get(clean, []))
        found, refs = [], []
        for ci, c in enumerate(conds):
            for i, (boxes, scores, labels) in enumerate(per_image[j][ci]):
                cand = scores >= AC_FLOOR
                sums["ac_sum"][j, ci, i] = scores[cand].sum()
                sums["ac_n"][j, ci, i] = cand.sum()
                sums["atc_n"][j, ci, i] = (scores >= thresholds[j]).sum() if math.isfinite(thresholds[j]) else np.nan
                mm, na, nb = _matches(per_image[j][c0][i], (boxes, scores, labels), d.threshold, d.threshold, iou)
                sums["self_m"][j, ci, i], sums["self_clean"][j, ci, i], sums["self_adv"][j, ci, i] = mm, na, nb
            sup = d.supported.get(c, np.zeros(d.refs[c].shape[1], bool)) if c in d.refs else None
            found.append(np.where(sup[None], d.found[c], 0) if sup is not None else np.zeros((n, n_classes)))
            refs.append(np.where(sup[None], d.refs[c], 0) if sup is not None else np.zeros((n, n_classes)))
            if c in d.matched:
                sums["matched"][j, ci], sums["confident"][j, ci] = d.matched[c], d.confident[c]
            for key in ("bos", "pcr"):
                v = getattr(d, key).get(c)
                if v is not None:
                    ok = np.isfinite(v)
                    sums[key][j, ci], sums[f"{key}_ok"][j, ci] = np.where(ok, v, 0.0), ok
        xi_found.append(np.stack(found, axis=0))  # C x N x K
        xi_refs.append(np.stack(refs, axis=0))
    sums["xi_found"] = np.stack(xi_found)  # M x C x N x K
    sums["xi_refs"] = np.stack(xi_refs)
    pairs = np.zeros((m_count, m_count, c_count, n))
    sizes = np.zeros((m_count, c_count, n))
    for ci in range(c_count):
        for i in range(n):
            for a in range(m_count):
                sizes[a, ci, i] = (per_image[a][ci][i][1] >= detectors[a].threshold).sum()
                for b in range(a + 1, m_count):
                    mm, _, _ = _matches(per_image[a][ci][i], per_image[b][ci][i], detectors[a].threshold,
                                        detectors[b].threshold, iou)
                    pairs[a, b, ci, i] = pairs[b, a, ci, i] = mm
    sums["sizes"] = sizes
    reachable = {k: all(len(getattr(d, "bos" if "bos" in k else "pcr")) > 0 for d in detectors) for k in NEEDS_FORWARDS}
    return Study([d.model for d in detectors], conds, clean, n, sums, ap, pseudo, pairs, thresholds, reachable)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def values(s: Study, weights: np.ndarray) -> dict[str, np.ndarray]:
    """R x N scene weights -> every estimator and target as M x R x C."""
    w = np.atleast_2d(np.asarray(weights, float))
    r, c0 = w.shape[0], s.conditions.index(s.clean)

    def wsum(a: np.ndarray) -> np.ndarray:  # M x C x N -> M x R x C
        return np.einsum("mcn,rn->mrc", np.nan_to_num(a), w)

    out: dict[str, np.ndarray] = {}
    found = np.einsum("mcnk,rn->mrck", s.sums["xi_found"], w)
    refs = np.einsum("mcnk,rn->mrck", s.sums["xi_refs"], w)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a cell without a supported class: NaN
        per_class = np.where(refs > 0, found / np.where(refs > 0, refs, 1), np.nan)
        defined = (s.sums["xi_refs"].sum(axis=2) > 0)[:, None]  # the supported classes: M x 1 x C x K
        xi = np.where(defined.any(-1), np.nanmean(np.where(defined, per_class, np.nan), axis=-1), np.nan) \
            if per_class.size else np.full((len(s.models), r, len(s.conditions)), np.nan)
    out["det_xi"] = xi
    out["det_precision"] = _ratio(wsum(s.sums["matched"]), wsum(s.sums["confident"]))
    with np.errstate(invalid="ignore", divide="ignore"):  # nothing found: F 0, whatever the precision (none: NaN)
        f = 2 * xi * out["det_precision"] / (xi + out["det_precision"])
        out["det_xi_f"] = np.where(xi == 0, 0.0, f)
    out["relative_det_xi"] = _ratio(xi, xi[:, :, c0:c0 + 1])
    out["ac"] = _ratio(wsum(s.sums["ac_sum"]), wsum(s.sums["ac_n"]))
    out["relative_ac"] = _ratio(out["ac"], out["ac"][:, :, c0:c0 + 1])
    atc = wsum(s.sums["atc_n"])
    out["atc"] = _ratio(atc, atc[:, :, c0:c0 + 1])
    out["self_agreement"] = _ratio(2 * wsum(s.sums["self_m"]), wsum(s.sums["self_clean"]) + wsum(s.sums["self_adv"]))
    m_count = len(s.models)
    committee = np.full((m_count, r, len(s.conditions)), np.nan)
    sizes = wsum(s.sums["sizes"])  # M x R x C
    for a in range(m_count):
        f1 = [_ratio(2 * np.einsum("cn,rn->rc", s.committee_pairs[a, b], w), sizes[a] + sizes[b])
              for b in range(m_count) if b != a]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a draw where no pair has a box: NaN, said as such
            committee[a] = np.nanmean(np.stack(f1), axis=0) if f1 else np.nan
    out["committee"] = committee
    for key in ("bos", "pcr"):
        out[key] = _ratio(wsum(s.sums[key]), wsum(s.sums[f"{key}_ok"]))
    out["relative_bos"] = _ratio(out["bos"], out["bos"][:, :, c0:c0 + 1])
    ap = np.full((m_count, r, len(s.conditions)), np.nan)
    pap = np.full((m_count, r, len(s.conditions)), np.nan)
    for j in range(m_count):
        for ci in range(len(s.conditions)):
            if s.ap[j][ci] is not None:
                ap[j, :, ci] = coco_resample.average_precision(s.ap[j][ci], w)
            pap[j, :, ci] = coco_resample.average_precision(s.pseudo[j][ci], w)
    out["pseudo_ap50"] = pap
    out["ap"] = ap
    clean_ap = ap[:, :, c0:c0 + 1]
    out["rpc"] = np.where(clean_ap >= RPC_MIN_CLEAN_AP, _ratio(ap, clean_ap), np.nan)  # 0.001 / 0.001 is no robustness
    out["clean_ap"] = np.repeat(ap[:, :, c0:c0 + 1], len(s.conditions), axis=2)
    return out


def compare(s: Study, resamples: int = 1000, confidence: float = 0.95, seed: int = 0, permutations: int = 10000
            ) -> tuple[list[dict], list[dict]]:
    """-> (cells, stats): one row per (ranked detector, adverse condition) with every estimator and target, and one
    per (estimator, target, scope) with scope each adverse condition, `within_mean`, `pooled` and `loio` (a linear
    map fitted on the other illuminations' cells, its MAE). See the module's docstring."""
    from pairedgta.metrics.bootstrap import resample_weights
    from pairedgta.metrics.estimator_study import (Resampled, _mean_over_conditions, drop_one_model,
                                                   illumination_folds, mae_with_intervals, model_draws,
                                                   permutation_pvalue, within_condition)
    from pairedgta.metrics.estimators import STATS
    from pairedgta.metrics.inference import holm
    from pairedgta.metrics.validity import _interval

    if len(s.models) < MIN_RANKED:
        raise ValueError(f"{len(s.models)} ranked detectors ({', '.join(s.models)}); at least {MIN_RANKED} are needed")
    adverse = [i for i, c in enumerate(s.conditions) if c != s.clean]
    if len(adverse) < 2:
        raise ValueError("at least 2 adverse conditions are needed")
    point = values(s, np.ones((1, s.n)))
    w = resample_weights(s.n, max(resamples, 0), seed).astype(float)
    boot = values(s, w) if len(w) else None
    jack = values(s, 1.0 - np.eye(s.n)) if len(w) and s.n >= 3 else None
    names = [e for e in ESTIMATORS if e not in NEEDS_FORWARDS or s.reachable.get(e)]
    cells = [{"model": m, "condition": s.conditions[i], "n_groups": s.n,
              **{k: float(point[k][j, 0, i]) for k in (*names, *TARGETS)}, "atc_threshold": float(s.atc_threshold[j])}
             for j, m in enumerate(s.models) for i in adverse]
    stats: list[dict] = []
    folds = illumination_folds([s.conditions[i] for i in adverse])
    for t in TARGETS:
        rows: dict[str, list[dict]] = {}
        judged: dict[str, Resampled] = {}
        # the detectors whose target (and detection xi, the yardstick) is defined in every adverse condition: an
        # rPC undefined below the clean-AP floor leaves that detector out of this target's rows (n_models says so)
        sub = np.flatnonzero(np.isfinite(point[t][:, 0][:, adverse]).all(1)
                             & np.isfinite(point["det_xi"][:, 0][:, adverse]).all(1))
        if len(sub) < 3:  # no rank statistic on fewer: every detector, its NaN cells make the correlations NaN
            sub = np.arange(len(s.models))
        draws, enough = model_draws(len(sub), len(w), seed)
        for e in names:
            px, py = point[e][sub][:, 0][:, adverse], point[t][sub][:, 0][:, adverse]
            base = {"estimator": e, "target": t, "n_models": len(sub), "n_groups": s.n,
                    "uses_clean_labels": e in USES_CLEAN_LABELS, "resamples": len(w), "confidence": confidence}
            per, mean, pooled = [], dict(base, scope="within_mean", n_conditions=len(adverse)), \
                dict(base, scope="pooled", n_conditions=len(adverse))
            bx = by = None
            if boot is not None:
                bx, by = boot[e][sub][:, :, adverse], boot[t][sub][:, :, adverse]
            for name, fn in STATS:
                p = within_condition(px[:, None], py[:, None], fn)[0]
                b = within_condition(bx, by, fn) if bx is not None else None
                for a, i in enumerate(adverse):
                    if len(per) <= a:
                        per.append(dict(base, scope=s.conditions[i], n_conditions=1))
                    lo, hi, _ = _interval(b[:, a], confidence) if b is not None else (math.nan, math.nan, 0)
                    per[a].update({name: float(p[a]), f"{name}_ci_low": lo, f"{name}_ci_high": hi})
                joint = None
                if bx is not None:
                    joint = np.where(enough, _mean_over_conditions(within_condition(bx, by, fn, draws)), np.nan)
                jk = () if jack is None else (
                    _mean_over_conditions(within_condition(jack[e][sub][:, :, adverse], jack[t][sub][:, :, adverse],
                                                           fn)),
                    drop_one_model(px, py, fn))
                stat = Resampled(float(np.mean(p)), joint, jk)
                if name == "spearman":
                    judged[e] = stat
                lo, hi = stat.interval(confidence)
                mean.update({name: stat.point, f"{name}_ci_low": lo, f"{name}_ci_high": hi})
                pooled.update({name: float(fn(px.T.reshape(1, -1), py.T.reshape(1, -1))[0])})
            mean["p_permutation"] = permutation_pvalue(px.T, py.T, permutations, seed)
            mean["permutations"] = permutations
            if folds:
                mae = mae_with_intervals(px, py, bx, by, None if jack is None else jack[e][sub][:, :, adverse],
                                         None if jack is None else jack[t][sub][:, :, adverse], draws if bx is not None
                                         else None, list(folds.values()), confidence)
                loio = dict(base, scope="loio", n_conditions=len(adverse), mae=mae["mae"][0][0],
                            mae_ci_low=mae["mae"][0][1], mae_ci_high=mae["mae"][0][2],
                            mae_baseline=mae["mae_baseline"][0][0])
                rows[e] = [*per, mean, pooled, loio]
            else:
                rows[e] = [*per, mean, pooled]
        means = {e: next(r for r in rows[e] if r["scope"] == "within_mean") for e in names}
        for e, h in zip(names, holm([means[e]["p_permutation"] for e in names])):
            means[e]["p_permutation_holm"] = h
        for e in names:
            d = judged[e] - judged["det_xi"]
            lo, hi = d.interval(confidence)
            means[e].update(spearman_minus_xi=d.point, spearman_minus_xi_ci_low=lo, spearman_minus_xi_ci_high=hi,
                            p_minus_xi=d.pvalue())
        for e, h in zip(names, holm([means[e]["p_minus_xi"] for e in names])):
            means[e]["p_minus_xi_holm"] = h
        stats += [{k: r.get(k, math.nan) for k in STAT_COLUMNS} for e in names for r in rows[e]]
    return cells, stats


__all__ = ["Detector", "ESTIMATORS", "NEEDS_FORWARDS", "STAT_COLUMNS", "Study", "TARGETS", "USES_CLEAN_LABELS",
           "compare", "prepare", "values"]
