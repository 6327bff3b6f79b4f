"""Is xi the best label-free judge of robustness? Label-free estimators of accuracy under shift, compared.

Every estimator gives one value per (model, adverse condition) cell; a larger value predicts a more
robust model. Each is checked, as `pairedgta.metrics.validity` checks xi, against the ground truth of the
embedded renderer: rPC = GT mIoU(adverse) / GT mIoU(clean) and the adverse GT mIoU.

- `xi`: label-free mean xi against the reference model's pseudo-labels (`validity.cell_measures`).
- `xi_precision`: xi's precision counterpart, label-free: per class, of the pixels the model predicts as c on the
  pseudo-label's valid pixels, the share whose pseudo-label is c; the class-wise mean as evaluate's xi_precision.csv
  (`validity.precision_measures`: over xi's mean classes that the model predicts with the same support). xi is a
  recall, blind to a model that paints one class everywhere; this is the side that sees it.
- `xi_f`: the harmonic mean of xi and its precision per class (2 retained / (reference + predicted)), class-wise
  mean over xi's mean classes: a class the model never predicts scores 0, as in xi.
- `xi_rel`, `ac_rel`, `atc_rel`: the relative versions, xi, AC and ATC under the condition divided by their
  clean value: a prediction of rPC, which divides the clean quality away as they do.
- `ac`: average confidence, the mean max-softmax probability (Hendrycks & Gimpel, ICLR 2017).
- `doc`: difference of confidences (Guillory et al., ICCV 2021): clean GT mIoU + AC(adverse) - AC(clean).
- `atc`: average thresholded confidence (Garg et al., ICLR 2022, max-confidence score): the threshold t is
  the smallest histogram edge at which the clean share of pixels with confidence >= t is at most the clean
  pixel accuracy, fitted on held-out clean scenes (the scenes split in two; each half scored with the other
  half's threshold); the estimate is the adverse share of pixels with confidence >= t. Share and accuracy
  count the same pixels: those labelled in the clean ground truth (and visible in the condition), the pixels
  the clean accuracy is measured on (`atc_labelled_share` in the cells: their share of all pixels).
- `entropy`: one minus the mean normalised predictive entropy H(p) / log K.
- `nuclear_norm`: the nuclear norm of the softmax matrix P (pixels x K) of a condition's pooled pixels (Deng et
  al., ICML 2023: confidence and dispersity at once), normalised as they normalise it, ||P||_* / sqrt(min(N, K) N),
  so that confident predictions spread evenly over the K classes score 1 (uniform ones 1 / K). From the summed
  per-image Grams P^T P: the singular values of P are the square roots of the Gram's eigenvalues.
- `energy`: the mean over pixels of logsumexp of the logits (the negative free energy at T = 1, Liu et al.,
  NeurIPS 2020); NaN for a family whose output is already a distribution (Mask2Former: no logits).
- `committee_agreement`: the mean over the other ranked models (other architectures and recipes) of the share
  of pixels on which the two predictions agree. Not GDE, which is the next one.
- `gde`: generalization disagreement equality (Jiang et al., ICLR 2022) on pixels: the share of pixels on which
  a model agrees with its twin, a second run of the same recipe differing in the seed only (the pairs named in
  metric.validity.twins). Defined for the twins only (NaN for the others); judged over those models alone
  (`pairedgta.metrics.estimator_study.compare`), with its difference to xi on the same models.
- `aline_s`, `aline_d`: agreement-on-the-line (Baek et al., NeurIPS 2022) on pixels: across the ranked
  models, the probit of each pair's pixel agreement under the condition is fitted as a line of its probit on
  the clean image (least squares over the pairs, per condition). ALine-S carries each model's probit clean
  pixel accuracy along that line; ALine-D solves, by least squares over all pairs at once, for the adverse
  accuracies u with (u_i + u_j) / 2 = probit agr_adv(i, j) + slope ((probit acc_i + probit acc_j) / 2 -
  probit agr_clean(i, j)). Both estimate adverse *pixel accuracy* (the quantity agreement is the analogue
  of), not mIoU.
- `self_agreement`: the share of pixels predicted as on the clean image of the same scene.
- `clean_miou`: the clean GT mIoU alone (accuracy on the line, Miller et al., ICML 2021).
- `clean_miou_x_self_agreement`: the clean GT mIoU times the self-agreement, the baseline that carries the
  clean quality (as xi does) into the plainest label-free measure of change.

`doc`, `atc`, `atc_rel`, `aline_s`, `aline_d`, `clean_miou` and `clean_miou_x_self_agreement` use the clean
condition's ground truth (the labelled source data these methods assume); no estimator uses a label of an
adverse condition.

How they are compared: pairedgta/metrics/estimator_study.py. Pure
numpy/scipy: the caller reads the files (the per-group sums of evaluate and its argmax predictions)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from pairedgta.metrics.validity import (GroupCounts, cell_measures, kendall_rows, precision_measures, spearman_rows,
                                        stack_passes)

ESTIMATORS = ("xi", "xi_rel", "ac", "ac_rel", "doc", "atc", "atc_rel", "entropy", "nuclear_norm", "energy",
              "committee_agreement", "gde", "aline_s", "aline_d", "self_agreement", "clean_miou", "clean_miou_x_self_agreement",
              "xi_precision", "xi_f")  # the last two since issue 64: appended, so the earlier rows keep their order
# clean ground truth; none uses adverse labels
USES_CLEAN_LABELS = frozenset({"doc", "atc", "atc_rel", "aline_s", "aline_d", "clean_miou",
                               "clean_miou_x_self_agreement"})
PROBIT_EPS = 1e-6  # shares are clipped to [eps, 1 - eps] before the probit: identical maps agree on all pixels
TARGETS = ("rpc", "gt_miou")
COUNT_ARRAYS = ("est_pixels", "est_conf_sum", "est_entropy_sum", "est_conf_hist", "est_agree_clean")
ABSENT_CLASS = 255  # predictions.npz: every pixel of a condition's absent image
MIN_RANKED = 4
COLUMNS = ("estimator", "target", "scope", "n_models", "n_undefined", "n_conditions", "n_cells", "n_groups", "spearman", "spearman_ci_low",
           "spearman_ci_high", "kendall", "kendall_ci_low", "kendall_ci_high", "spearman_model_ci_low",
           "spearman_model_ci_high", "kendall_model_ci_low", "kendall_model_ci_high", "p_permutation", "permutations",
           "p_permutation_holm", "mae", "mae_ci_low", "mae_ci_high", "mae_baseline", "mae_baseline_ci_low",
           "mae_baseline_ci_high", "spearman_minus_xi", "spearman_minus_xi_ci_low",
           "spearman_minus_xi_ci_high", "p_minus_xi", "p_minus_xi_holm", "uses_clean_labels", "resamples",
           "confidence")  # of compare's `stats`
STATS: tuple[tuple[str, Callable[[np.ndarray, np.ndarray], np.ndarray]], ...] = (
    ("spearman", spearman_rows), ("kendall", kendall_rows))


@dataclass(frozen=True)
class EstimatorCounts:
    """One model's per-group sums for the label-free estimators (evaluate's `est_*` arrays)."""

    model: str
    conditions: tuple[str, ...]
    pixels: np.ndarray       # G x C: pixels scored
    conf_sum: np.ndarray     # G x C: sum of the max softmax probability
    entropy_sum: np.ndarray  # G x C: sum of H(p) / log K
    conf_hist: np.ndarray    # G x C x B: max softmax probability in B equal bins on [0, 1]
    agree_clean: np.ndarray  # G x C: pixels predicted as on the clean image
    group_ids: tuple[str, ...] = ()
    # optional (None where an entry lacks them): the histogram of the pixels labelled in the clean ground truth
    # (ATC); the K x K Gram of the softmax matrix (nuclear norm); the summed logsumexp of the logits (energy)
    conf_hist_labelled: np.ndarray | None = None  # G x C x B
    gram: np.ndarray | None = None                # G x C x K x K
    energy_sum: np.ndarray | None = None          # G x C

    @classmethod
    def from_arrays(cls, model: str, a: Mapping[str, np.ndarray]) -> "EstimatorCounts":
        missing = [k for k in COUNT_ARRAYS if k not in a]
        if missing:
            raise ValueError(f"model {model}: no {', '.join(missing)} in the group counts")
        ids = tuple(str(g) for g in a["group_id"]) if "group_id" in a else ()
        optional = {k: np.asarray(a[f"est_{k}"]) for k in OPTIONAL if f"est_{k}" in a}
        return cls(model, tuple(str(c) for c in a["conditions"]), *(np.asarray(a[k]) for k in COUNT_ARRAYS), ids,
                   **optional)


OPTIONAL = ("conf_hist_labelled", "gram", "energy_sum")


def concat_counts(parts: Iterable[EstimatorCounts]) -> EstimatorCounts:
    """Groups of several passes of one model, stacked (as `validity.concat_groups`); an optional array only
    where every pass has it."""
    parts = list(parts)
    arrays, ids = stack_passes(parts, ("pixels", "conf_sum", "entropy_sum", "conf_hist", "agree_clean"))
    have = tuple(k for k in OPTIONAL if all(getattr(p, k) is not None for p in parts))
    optional = dict(zip(have, stack_passes(parts, have)[0])) if have else {}
    return EstimatorCounts(parts[0].model, parts[0].conditions, *arrays, ids, **optional)


def _weigh(w: np.ndarray, a: np.ndarray) -> np.ndarray:
    """R x G weights applied to G x ... per-group sums -> R x ..."""
    a = np.asarray(a, float)
    return (np.asarray(w, float) @ a.reshape(a.shape[0], -1)).reshape((len(w),) + a.shape[1:])


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)


def average_confidence(c: EstimatorCounts, w: np.ndarray) -> np.ndarray:
    """AC per (resample, condition): pooled mean max-softmax probability."""
    return _ratio(_weigh(w, c.conf_sum), _weigh(w, c.pixels))


def entropy_score(c: EstimatorCounts, w: np.ndarray) -> np.ndarray:
    """1 - pooled mean normalised entropy per (resample, condition): higher = more confident."""
    return 1.0 - _ratio(_weigh(w, c.entropy_sum), _weigh(w, c.pixels))


def nuclear_norm_score(c: EstimatorCounts, w: np.ndarray) -> np.ndarray:
    """||P||_* / sqrt(min(N, K) N) per (resample, condition) of the pooled pixels' softmax matrix P (N x K), from
    the weighted sum of the per-image Grams (module docstring); NaN without Grams."""
    pixels = _weigh(w, c.pixels)
    if c.gram is None:
        return np.full(pixels.shape, np.nan)
    gram = _weigh(w, c.gram)                                      # R x C x K x K
    ok = np.isfinite(gram).all(axis=(-2, -1))
    eig = np.linalg.eigvalsh(np.where(ok[..., None, None], gram, 0.0))
    nuclear = np.sqrt(np.clip(eig, 0.0, None)).sum(axis=-1)      # the Gram is PSD: negatives are rounding
    bound = np.sqrt(np.minimum(pixels, gram.shape[-1]) * pixels)
    return np.where(ok, _ratio(nuclear, bound), np.nan)


def energy_score(c: EstimatorCounts, w: np.ndarray) -> np.ndarray:
    """Pooled mean logsumexp of the logits per (resample, condition); NaN without logits."""
    if c.energy_sum is None:
        return np.full(_weigh(w, c.pixels).shape, np.nan)
    return _ratio(_weigh(w, c.energy_sum), _weigh(w, c.pixels))


def self_agreement(c: EstimatorCounts, w: np.ndarray) -> np.ndarray:
    """Pooled share of pixels predicted as on the clean image, per (resample, condition)."""
    return _ratio(_weigh(w, c.agree_clean), _weigh(w, c.pixels))


def pixel_accuracy(cm: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Pooled pixel accuracy of G x C x K x K confusion matrices, per (resample, condition)."""
    m = _weigh(w, cm)
    return _ratio(np.trace(m, axis1=-2, axis2=-1), m.sum((-2, -1)))


def atc_threshold(clean_hist: np.ndarray, accuracy: np.ndarray) -> np.ndarray:
    """Index k (0..B) of the ATC threshold edge k / B per row of ... x B clean histograms: the smallest
    edge where the share of pixels with confidence >= k / B is at most `accuracy` (...). -1 where the
    histogram is empty or the accuracy undefined."""
    h = np.asarray(clean_hist, float)
    acc = np.asarray(accuracy, float)
    tail = _tails(h)
    total = tail[..., 0]
    share = _ratio(tail, total[..., None])
    with np.errstate(invalid="ignore"):
        k = np.argmax(share <= acc[..., None] + 1e-12, axis=-1)  # share[B] = 0: always found when defined
    return np.where((total > 0) & np.isfinite(acc), k, -1)


def _tails(h: np.ndarray) -> np.ndarray:
    """... x B histogram -> ... x (B + 1): counts at or above each edge k / B (the last is 0)."""
    return np.concatenate([np.cumsum(h[..., ::-1], axis=-1)[..., ::-1], np.zeros(h.shape[:-1] + (1,), h.dtype)], axis=-1)


def atc(hist: np.ndarray, cm: np.ndarray, clean: int, w: np.ndarray,
        fit: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """-> (ATC per (resample, condition), threshold per resample), from G x C x B confidence histograms
    and the clean condition's G x C x K x K confusion matrices (its pixel accuracy). The threshold is fitted
    on the clean images of the groups weighted by `fit` (R x G; default `w`, the groups scored)."""
    above, total, k = _atc_parts(hist, cm, clean, w, w if fit is None else fit)
    bins = np.asarray(hist).shape[-1]
    return np.where(k[:, None] >= 0, _ratio(above, total), np.nan), np.where(k >= 0, k / bins, np.nan)


def _atc_parts(hist: np.ndarray, cm: np.ndarray, clean: int, w: np.ndarray,
               fit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (pixels at or above the threshold, pixels, R x C, of the groups weighted by `w`; the threshold's
    edge index k per resample, fitted on the clean images weighted by `fit`, -1 where undefined)."""
    w, fit = np.asarray(w, float), np.asarray(fit, float)
    hist = np.asarray(hist)
    tails = _tails(hist)                      # G x C x (B + 1), per group: cheap to weigh at one edge
    k = atc_threshold(_weigh(fit, hist[:, clean]), pixel_accuracy(np.asarray(cm)[:, clean : clean + 1], fit)[:, 0])
    above = np.einsum("rg,gcr->rc", w, tails[:, :, np.maximum(k, 0)].astype(float))  # R x C
    return above, _weigh(w, tails[..., 0]), k


ATC_FOLDS = 2


def atc_held_out(hist: np.ndarray, cm: np.ndarray, clean: int, w: np.ndarray,
                 folds: int = ATC_FOLDS) -> tuple[np.ndarray, np.ndarray]:
    """ATC with its threshold fitted on held-out clean scenes, as Garg et al. fit it on held-out labelled
    source data: the groups are split into `folds` by position (group g in fold g mod folds), and each
    fold's images are scored with the threshold fitted on the clean images of the other folds, never on
    their own scenes. -> (ATC per (resample, condition), the mean of the folds' thresholds per resample);
    NaN where a fold's threshold is undefined (a resample that drew none of the other folds' groups)."""
    w = np.asarray(w, float)
    n = np.asarray(hist).shape[0]
    bins = np.asarray(hist).shape[-1]
    if n < folds:
        return np.full((len(w), np.asarray(hist).shape[1]), np.nan), np.full(len(w), np.nan)
    fold = np.arange(n) % folds
    above, total, thresholds = 0.0, 0.0, []
    for f in range(folds):
        own = (fold == f).astype(float)
        a, t, k = _atc_parts(hist, cm, clean, w * own, w * (1 - own))
        above = above + np.where(k[:, None] >= 0, a, np.nan)
        total = total + t
        thresholds.append(np.where(k >= 0, k / bins, np.nan))
    return _ratio(above, total), np.mean(thresholds, axis=0)


def pairwise_agreement(sources: Sequence[Mapping[str, np.ndarray]], n_groups: int,
                       key: Callable[[int], str] = lambda g: f"g{g:05d}") -> tuple[np.ndarray, np.ndarray]:
    """Pixel agreement between every pair of M models, per group and condition, from their argmax maps
    (`sources[m][key(g)]`: C x H x W class ids, 255 where the image is absent; read one group at a time,
    so a lazily loaded npz holds one group per model in memory). -> (agree, scored), both G x C x M x M:
    pixels where the two predict the same class, and pixels both predicted (the diagonal: each model's)."""
    m_count = len(sources)
    agree = scored = None
    for g in range(n_groups):
        have = [key(g) in s for s in sources]
        if not any(have):  # no image of the group was predicted (evaluate writes no key): it scores nothing
            continue
        if not all(have):
            raise ValueError(f"group {key(g)}: predicted by some models only")
        preds = [np.asarray(s[key(g)]) for s in sources]
        shapes = {p.shape for p in preds}
        if len(shapes) != 1 or len(preds[0].shape) != 3:
            raise ValueError(f"group {key(g)}: the models' predictions have shapes {sorted(shapes)}, not one C x H x W")
        flat = [p.reshape(p.shape[0], -1) for p in preds]
        valid = [f != ABSENT_CLASS for f in flat]
        if agree is None:
            agree = np.zeros((n_groups, preds[0].shape[0], m_count, m_count), np.int64)
            scored = np.zeros_like(agree)
        elif preds[0].shape[0] != agree.shape[1]:
            raise ValueError(f"group {key(g)}: {preds[0].shape[0]} conditions, not {agree.shape[1]}")
        for a in range(m_count):
            agree[g, :, a, a] = scored[g, :, a, a] = np.count_nonzero(valid[a], axis=-1)
            for b in range(a + 1, m_count):
                same = np.count_nonzero((flat[a] == flat[b]) & valid[a], axis=-1)
                both = np.count_nonzero(valid[a] & valid[b], axis=-1)
                agree[g, :, a, b] = agree[g, :, b, a] = same
                scored[g, :, a, b] = scored[g, :, b, a] = both
    if agree is None:
        return np.zeros((n_groups, 0, m_count, m_count), np.int64), np.zeros((n_groups, 0, m_count, m_count), np.int64)
    return agree, scored


def committee_agreement(agree: np.ndarray, scored: np.ndarray, w: np.ndarray) -> np.ndarray:
    """M x R x C: per model the mean over the other models of the pooled pixel agreement share (a committee
    of other architectures, not GDE's second seed of the same recipe)."""
    share = _ratio(_weigh(w, agree), _weigh(w, scored))   # R x C x M x M
    m_count = share.shape[-1]
    share = np.where(np.eye(m_count, dtype=bool), np.nan, share)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # one model: no other to agree with
        return np.moveaxis(np.nanmean(share, axis=-1), -1, 0)


def gde(agree: np.ndarray, scored: np.ndarray, w: np.ndarray, twin: Sequence[int]) -> np.ndarray:
    """M x R x C: per model the pooled pixel agreement share with its twin (`twin[j]`: the twin's index among
    the M models, -1 for none: NaN)."""
    share = _ratio(_weigh(w, agree), _weigh(w, scored))   # R x C x M x M
    out = np.full((share.shape[-1], *share.shape[:2]), np.nan)
    for j, k in enumerate(twin):
        if k >= 0:
            out[j] = share[:, :, j, k]
    return out


def twin_indices(names: Sequence[str], twins: Iterable[Sequence[str]]) -> np.ndarray:
    """Each model's twin's index among `names` (-1 where it has none, or its twin is not among them), from
    the pairs of metric.validity.twins; a model in two pairs is refused (a twin is one other run)."""
    index = {n: i for i, n in enumerate(names)}
    out = np.full(len(names), -1)
    seen: set[str] = set()
    for pair in twins:
        pair = [str(x) for x in pair]
        if len(pair) != 2 or pair[0] == pair[1]:
            raise ValueError(f"metric.validity.twins: {pair} is not a pair of two models; write [model, its twin]")
        if seen & set(pair):
            raise ValueError(f"metric.validity.twins: {', '.join(sorted(seen & set(pair)))} is in two pairs; "
                             "a model has at most one twin")
        seen |= set(pair)
        a, b = pair
        if a in index and b in index:
            out[index[a]], out[index[b]] = index[b], index[a]
    return out


def _probit(p: np.ndarray) -> np.ndarray:
    from scipy.special import ndtri

    return ndtri(np.clip(np.asarray(p, float), PROBIT_EPS, 1 - PROBIT_EPS))


def aline(agree: np.ndarray, scored: np.ndarray, accuracy: np.ndarray, clean: int,
          w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ALine-S and ALine-D (module docstring), each M x R x C, from the pairwise pixel agreement of the M
    models (`pairwise_agreement`: G x C x M x M), their clean pixel accuracy (M x R) and group weights R x G.
    NaN where the pairs' clean agreements do not vary (no line to fit) or a pair's agreement is undefined."""
    from scipy.special import ndtr

    share = _ratio(_weigh(w, agree), _weigh(w, scored))            # R x C x M x M
    m = share.shape[-1]
    i, j = np.triu_indices(m, k=1)
    x = _probit(share[:, clean, i, j])[:, None, :]                  # R x 1 x P: the clean (ID) agreements
    y = _probit(share[:, :, i, j])                                  # R x C x P: under each condition
    x = np.broadcast_to(x, y.shape)
    ok = np.isfinite(x) & np.isfinite(y)
    count = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.where(ok, x, 0).sum(-1) / count
        my = np.where(ok, y, 0).sum(-1) / count
        dx = np.where(ok, x - mx[..., None], 0)
        sxx, sxy = (dx * dx).sum(-1), (dx * np.where(ok, y - my[..., None], 0)).sum(-1)
        slope = np.where((count >= 2) & (sxx > 1e-12), sxy / np.where(sxx > 0, sxx, 1), np.nan)   # R x C
    bias = my - slope * mx
    acc = _probit(accuracy)                                          # M x R
    aline_s = ndtr(slope[None] * acc[:, :, None] + bias[None])       # M x R x C
    design = np.zeros((len(i), m))
    design[np.arange(len(i)), i] = design[np.arange(len(i)), j] = 0.5
    solve = np.linalg.pinv(design)                                   # M x P: least squares over the pairs
    rhs = y + slope[..., None] * ((acc.T[:, i] + acc.T[:, j])[:, None, :] / 2 - x)   # R x C x P
    aline_d = ndtr(np.moveaxis(rhs @ solve.T, -1, 0))                # M x R x C (NaN where a pair is undefined)
    return aline_s, aline_d


def model_values(g: GroupCounts, c: EstimatorCounts, weights: np.ndarray, clean: str, include: np.ndarray,
                 absent: str = "nan", min_images: int = 0, min_pixels: int = 0,
                 rpc_floor: float = 0.0) -> dict[str, np.ndarray]:
    """One model's estimators but those that need the other models (committee agreement, ALine) and the
    targets, R x C, plus `atc_threshold` (R: the mean of the held-out folds' thresholds):
    what evaluate writes per model (`estimators.csv`) and the comparison stacks over models. rPC is
    undefined below the clean-mIoU floor `rpc_floor` (`validity.cell_measures`)."""
    if c.model != g.model or c.conditions != g.conditions or c.pixels.shape[0] != g.cm.shape[0]:
        raise ValueError(f"model {g.model}: the estimator sums cover other groups, conditions or models")
    w = np.asarray(weights, float)
    c0 = g.conditions.index(clean)
    cm = cell_measures(g, w, clean, include, absent, min_images, min_pixels, rpc_floor)
    ac = average_confidence(c, w)
    # share and accuracy over the same pixels: the labelled ones, where the entry has their histogram
    score, threshold = atc_held_out(c.conf_hist if c.conf_hist_labelled is None else c.conf_hist_labelled, g.cm, c0, w)
    agreement = self_agreement(c, w)
    return {"xi": cm["xi_mean"], "xi_rel": relative(cm["xi_mean"], c0), "ac": ac, "ac_rel": relative(ac, c0),
            "doc": cm["gt_miou_clean"] + ac - ac[:, c0 : c0 + 1], "atc": score, "atc_rel": relative(score, c0),
            "entropy": entropy_score(c, w), "nuclear_norm": nuclear_norm_score(c, w), "energy": energy_score(c, w),
            "self_agreement": agreement, "clean_miou": cm["gt_miou_clean"],
            "clean_miou_x_self_agreement": cm["gt_miou_clean"] * agreement, "rpc": cm["rpc"], "gt_miou": cm["gt_miou"],
            "gt_miou_clean": cm["gt_miou_clean"], "atc_threshold": threshold,
            **{k.removesuffix("_mean"): v for k, v in precision_measures(g, w, include, absent, min_images, min_pixels).items()}}


def relative(values: np.ndarray, clean: int) -> np.ndarray:
    """R x C values divided by their clean column (NaN where that is 0 or undefined)."""
    values = np.asarray(values, float)
    return _ratio(values, np.broadcast_to(values[:, clean : clean + 1], values.shape))


def estimator_values(models: Sequence[GroupCounts], counts: Sequence[EstimatorCounts], agree: np.ndarray,
                     scored: np.ndarray, weights: np.ndarray, clean: str, include: np.ndarray, absent: str = "nan",
                     min_images: int = 0, min_pixels: int = 0, rpc_floor: float = 0.0,
                     twin: Sequence[int] | None = None) -> dict[str, np.ndarray]:
    """Every estimator and target, M x R x C, for group weights R x G (a row of ones = the data itself),
    plus `atc_threshold` (M x R). `agree`/`scored`: `pairwise_agreement` over the same models, in order;
    `twin`: `twin_indices` of the same models (None: no twins, GDE all NaN)."""
    if agree.shape[-1] != len(models) or agree.shape[0] != models[0].cm.shape[0]:
        raise ValueError(f"pairwise agreement of {agree.shape[-1]} models over {agree.shape[0]} groups for "
                         f"{len(models)} models over {models[0].cm.shape[0]} groups")
    w = np.asarray(weights, float)
    out: dict[str, list[np.ndarray]] = {}
    for g, c in zip(models, counts):
        for k, v in model_values(g, c, w, clean, include, absent, min_images, min_pixels, rpc_floor).items():
            out.setdefault(k, []).append(v)
    stacked = {k: np.stack(v) for k, v in out.items()}
    stacked["committee_agreement"] = committee_agreement(agree, scored, w)
    stacked["gde"] = gde(agree, scored, w, [-1] * len(models) if twin is None else twin)
    c0 = models[0].conditions.index(clean)
    accuracy = np.stack([pixel_accuracy(np.asarray(g.cm)[:, c0 : c0 + 1], w)[:, 0] for g in models])   # M x R
    stacked["aline_s"], stacked["aline_d"] = aline(agree, scored, accuracy, c0, w)
    return stacked
