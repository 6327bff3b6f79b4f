"""Evaluate's per-group reduction kernels, in torch on whatever device the predictions are (one code path for the
CPU and a GPU), which the registered metrics' `update` call (`registry.METRICS`): from the label maps, max
probabilities and entropies of a group's conditions (`PixelMaps`) the xi counts, the confusion matrices, the
agreement counts, phi per class and the label-free estimators' sums and histograms. Only these small arrays (and the uint8 label maps) cross to the host, in one copy per group that
does not wait for the GPU (`HostCopy`); the host reads it a group later, while the next group computes.

Counts are integers, so they are the same on any device and in any order. The two float sums (max probability
and entropy per image) are float64 sums of float32 values; they add in the order numpy's `np.sum` adds (pairwise
over blocks of 8192, the blocks in sequence: `ordered_sum`), the order of the former host path, so the CPU gives
bit-identical numbers and a GPU adds its maps in the same order as the CPU.

Counting on a GPU is by `scatter_add_` into a zeroed tensor, not `torch.bincount`: on CUDA bincount reads the
input's minimum and maximum back to the host (two synchronisations per call); on the CPU it is bincount. Invalid
pixels go to one extra bin that is dropped, instead of boolean indexing (whose output size the host must know)."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from pairedgta.cityscapes import IGNORE_INDEX, NUM_CLASSES
from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

CONF_BINS = 1000  # the max-probability histogram ATC's threshold is read from: edges k / 1000
SUM_BLOCK = 8192  # numpy's buffer: np.sum(float32, dtype=float64) sums blocks of this many pairwise, in sequence
_LEAF = 128       # numpy's pairwise_sum unrolls blocks of up to this many values with 8 accumulators


# -- counting -------------------------------------------------------------------------------------------------
LANES = 64  # on a GPU each bin is counted in this many places (pixel index mod LANES), then summed


def count(keys: torch.Tensor, bins: int, lanes: int | None = None) -> torch.Tensor:
    """Occurrences of 0 .. bins-1 in `keys` (int64, any shape; a key == bins is a dropped pixel): bincount
    without a host synchronisation. On a GPU the atomic adds of a few bins (19 classes; most pixels in the top
    confidence bin) would queue on the same addresses: neighbouring pixels count into LANES separate copies."""
    keys = keys.reshape(-1)
    if keys.device.type == "cpu" and not lanes:  # no host to wait for: bincount's one pass
        return torch.bincount(keys, minlength=bins + 1)[:bins]
    lanes = lanes or LANES  # a power of two
    if lanes > 1:
        lane = torch.arange(keys.shape[0], device=keys.device, dtype=torch.int64).bitwise_and_(lanes - 1)
        keys = lane.mul_(bins + 1).add_(keys)  # lane-major: the copies of a bin lie far apart
    out = torch.zeros(lanes * (bins + 1), dtype=torch.int64, device=keys.device)
    out.scatter_add_(0, keys, torch.ones((), dtype=torch.int64, device=keys.device).expand(keys.shape[0]))
    return out.view(lanes, bins + 1).sum(dim=0)[:bins] if lanes > 1 else out[:bins]


def _in_range(labels: torch.Tensor, num_classes: int, ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """Pixels whose label is a class (0 <= label < K, not void); one comparison for uint8 maps."""
    if labels.dtype == torch.uint8 and num_classes <= ignore_index:
        return labels < num_classes
    return (labels >= 0) & (labels < num_classes) & (labels != ignore_index)


def _count_keyed(index: torch.Tensor, valid: torch.Tensor, n: int, width: int) -> torch.Tensor:
    """N x width counts of `index` (N x H x W int64, 0 <= index < width where valid; modified in place) over the
    pixels where `valid` (broadcastable to it), one count for all N images."""
    index += _image_offsets(n, width, index.device)
    index.masked_fill_(~valid, n * width)  # the dropped bin
    return count(index, n * width).view(n, width)


def _image_offsets(n: int, width: int, device: Any) -> torch.Tensor:
    return (torch.arange(n, device=device, dtype=torch.int64) * width).view(n, 1, 1)


def xi_counts(reference: torch.Tensor, pred: torch.Tensor, num_classes: int = NUM_CLASSES,
              ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """N x K x 2 per image: reference pixels of class k whose prediction differs [.., 0] and equals [.., 1] (so
    retained = [..., 1], reference = sum over the last axis): `reference_consistency_counts` of N images at once.
    `reference` is N x H x W, or H x W for a reference all N share (computed once, not per image)."""
    n, k = pred.shape[0], num_classes
    index = (pred == reference) + reference.long() * 2  # int64 N x H x W; the rest at the reference's own size
    return _count_keyed(index, _in_range(reference, k, ignore_index), n, 2 * k).view(n, k, 2)


def predicted_counts(reference: torch.Tensor, pred: torch.Tensor, num_classes: int = NUM_CLASSES,
                     ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """N x K per image: the pixels predicted as class k among the reference's valid pixels (those `xi_counts`
    counts), the denominator of xi's precision: `reference_consistency.predicted_counts` of N images at once.
    `reference` is N x H x W or H x W (shared by the N images)."""
    return class_counts(pred, _in_range(reference, num_classes, ignore_index), num_classes)


def confusion(target: torch.Tensor, pred: torch.Tensor, num_classes: int = NUM_CLASSES,
              ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """N x K x K confusion matrices (truth x prediction) of N images: `confusion_counts` of each."""
    n, k = pred.shape[0], num_classes
    valid = _in_range(target, k, ignore_index) & _in_range(pred, k, ignore_index) if pred.dtype == torch.uint8 else (
        _in_range(target, k, ignore_index) & (pred >= 0) & (pred < k))
    index = target.long() * k + pred
    return _count_keyed(index, valid, n, k * k).view(n, k, k)


def class_counts(labels: torch.Tensor, keep: torch.Tensor, num_classes: int = NUM_CLASSES) -> torch.Tensor:
    """N x K: per image the pixels of each class where `keep` (phi: `prediction_mass_from_labels`)."""
    valid = keep & ((labels < num_classes) if labels.dtype == torch.uint8 else (labels >= 0) & (labels < num_classes))
    return _count_keyed(labels.long(), valid, labels.shape[0], num_classes)


def confidence_histogram(confidence: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
    """N x CONF_BINS: per image the max probabilities (of the pixels where `keep`, default all) in bins
    [k/1000, (k+1)/1000), 1.0 in the last; as the host path binned (float64 product, truncated). Out-of-range
    values (a NaN that check_finite reports at the end of the stage) are clamped into range so that counting
    never fails before that report."""
    n = confidence.shape[0]
    bins = (confidence.double() * CONF_BINS).long().clamp_(0, CONF_BINS - 1)
    keys = bins + _image_offsets(n, CONF_BINS, bins.device)
    if keep is not None:
        keys.masked_fill_(~keep, n * CONF_BINS)  # the dropped bin
    return count(keys, n * CONF_BINS).view(n, CONF_BINS)


# -- float sums in numpy's order -------------------------------------------------------------------------------
def _leaf_sum(x: torch.Tensor) -> torch.Tensor:
    """numpy's pairwise_sum for n <= 128 along the last axis: 8 running sums, combined as a tree, then the rest."""
    n = x.shape[-1]
    if n < 8:
        res = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        for i in range(n):
            res = res + x[..., i]
        return res
    m = n - n % 8
    r = x[..., 0:8]
    for i in range(8, m, 8):
        r = r + x[..., i : i + 8]
    res = ((r[..., 0] + r[..., 1]) + (r[..., 2] + r[..., 3])) + ((r[..., 4] + r[..., 5]) + (r[..., 6] + r[..., 7]))
    for i in range(m, n):
        res = res + x[..., i]
    return res


def _pairwise(x: torch.Tensor) -> torch.Tensor:
    """numpy's pairwise_sum along the last axis (float64), vectorised where the halving is regular."""
    n = x.shape[-1]
    if n <= _LEAF:
        return _leaf_sum(x)
    leaves = n // _LEAF
    if n % _LEAF == 0 and leaves & (leaves - 1) == 0:  # 128 * 2^j values: halves all the way down to 128
        v = x.reshape(*x.shape[:-1], leaves, 16, 8)
        r = v[..., 0, :]
        for i in range(1, 16):
            r = r + v[..., i, :]
        s = ((r[..., 0] + r[..., 1]) + (r[..., 2] + r[..., 3])) + ((r[..., 4] + r[..., 5]) + (r[..., 6] + r[..., 7]))
        while s.shape[-1] > 1:
            s = s[..., 0::2] + s[..., 1::2]
        return s[..., 0]
    half = n // 2
    half -= half % 8
    return _pairwise(x[..., :half]) + _pairwise(x[..., half:])


def block_sums(values: torch.Tensor) -> torch.Tensor:
    """N x blocks float64: per image (the first axis; the rest flattened, C order) the pairwise sums of its
    blocks of SUM_BLOCK values, on the device. `ordered_sum` adds them up on the host."""
    x = values.reshape(values.shape[0], -1).double()
    n, size = x.shape
    full = size // SUM_BLOCK
    parts = []
    if full:
        parts.append(_pairwise(x[:, : full * SUM_BLOCK].reshape(n, full, SUM_BLOCK)))
    if size % SUM_BLOCK or not full:
        parts.append(_pairwise(x[:, full * SUM_BLOCK :]).unsqueeze(1))
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


def ordered_sum(blocks: Sequence[float] | np.ndarray) -> float:
    """One image's block sums (`block_sums`), added in sequence from 0.0 as numpy's reduction adds them."""
    total = 0.0
    for b in np.asarray(blocks, dtype=np.float64).tolist():
        total += b
    return total


def image_sums(values: torch.Tensor) -> list[float]:
    """float(np.sum(values[i], dtype=np.float64)) for each image i, bit for bit, computed on the device."""
    return [ordered_sum(row) for row in block_sums(values).cpu().numpy()]


_STREAMS: dict[tuple[str, str], Any] = {}


def side_stream(device: Any, role: str) -> Any:
    """One CUDA stream per device and role (h2d: inputs in, d2h: results out), beside the compute stream."""
    key = (str(device), role)
    if key not in _STREAMS:
        _STREAMS[key] = torch.cuda.Stream(device)
    return _STREAMS[key]


class HostCopy:
    """Device tensors copied to the host without waiting for the device: on a GPU into pinned memory with
    `non_blocking`, an event marks their arrival; `get()` waits for that event only (on the CPU it is all there)."""

    def __init__(self, tensors: Mapping[str, torch.Tensor]) -> None:
        self.event = None
        first = next(iter(tensors.values()), None)
        if first is not None and first.device.type == "cuda":
            # on a stream of their own, so the next group's kernels need not wait behind the copies
            stream = side_stream(first.device, "d2h")
            stream.wait_stream(torch.cuda.current_stream(first.device))
            with torch.cuda.stream(stream):
                self.host = {k: v.to("cpu", non_blocking=True) for k, v in tensors.items()}
                for v in tensors.values():
                    v.record_stream(stream)  # not reused by the compute stream before the copy is done
                self.event = torch.cuda.Event()
                self.event.record(stream)
        else:
            self.host = {k: v.cpu() for k, v in tensors.items()}

    def get(self) -> dict[str, np.ndarray]:
        if self.event is not None:
            self.event.synchronize()
            self.event = None
        return {k: v.numpy() for k, v in self.host.items()}


__all__ = ["CONF_BINS", "SUM_BLOCK", "LANES", "count", "xi_counts", "predicted_counts", "confusion", "class_counts", "confidence_histogram",
           "block_sums", "ordered_sum", "image_sums", "HostCopy"]
