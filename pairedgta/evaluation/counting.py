"""One group's counts from one forward pass per image, one record per registered metric (`registry.METRICS`):
per (reference source, condition) the retained and reference pixels per class (xi), the confusion matrix
against ground truth (IoU), the agreement counts, the prediction mass phi per class (rho_valid), the label-free
estimators' sums, and whatever a metric added since records. Plain numbers
only (a shard job's partial sums are lists of these), never the predictions' probabilities, so memory
does not grow with the image size times the number of images.

The metrics' updates run where the model runs (torch on the CPU or a GPU, on one shared `GroupContext`); what
crosses to the host per group is the uint8 label maps and those counts, copied without waiting for the device.
On a GPU the groups are pipelined: group g+1's images are copied to the device (a side stream, pinned memory)
while group g computes, and group g-1's results are read on the host meanwhile."""
from __future__ import annotations

import gc
from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np
from tqdm import tqdm

from pairedgta.datasets import LabelMaps, PairedDataset
from pairedgta.errors import DataError
from pairedgta.evaluation import entry, reductions, registry
from pairedgta.evaluation.inputs import GroupInputs, load_groups, pack_group
from pairedgta.evaluation.metric import GT, PSEUDO_LABEL, Group, GroupContext
from pairedgta.evaluation.reductions import CONF_BINS
from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none
F = lazy_module("torch.nn.functional")


def _device(segmenter: Any) -> Any:
    return getattr(segmenter, "device", None) or torch.device("cpu")


def stage_inputs(packed: dict[str, Any], device: Any) -> dict[str, Any]:
    """A packed group's tensors (`inputs.pack_group`) on `device`; on a GPU on a side stream, so the copy
    overlaps the forward of the group before, with an event the compute stream waits for before using them."""
    from pairedgta.models.base import to_device

    tensors = {k: v for k, v in packed.items() if isinstance(v, torch.Tensor)}
    if device.type != "cuda":
        return {**packed, **{k: to_device(v, device) for k, v in tensors.items()}}
    stream = reductions.side_stream(device, "h2d")
    with torch.cuda.stream(stream):
        moved = {k: to_device(v, device) for k, v in tensors.items()}
        ready = torch.cuda.Event()
        ready.record(stream)
    return {**packed, **moved, "_ready": ready}


def _use(inputs: dict[str, Any]) -> None:
    """Make the compute stream wait for the side stream's copy, and keep the copied tensors' memory from being
    reused before the compute stream is done with them."""
    ready = inputs.pop("_ready", None)
    if ready is None:
        return
    stream = torch.cuda.current_stream()
    stream.wait_event(ready)
    for v in inputs.values():
        if isinstance(v, torch.Tensor) and v.is_cuda:
            v.record_stream(stream)


def _maps(segmenter: Any, images: Any, batch: int, needs: set[str] = frozenset()) -> dict[str, Any]:
    """labels (uint8), max probability and normalised entropy of the N images, N x H x W on the model's device,
    in forward batches of `batch` (the same batches as ever, so the same numbers on the CPU); and from the same
    forward what the registered metrics `need` ("energy", "gram"; None where the model gives none)."""
    names = ("labels", "confidence", "entropy", "energy", "gram")
    parts: dict[str, list[Any]] = {k: [] for k in names}
    for start in range(0, images.shape[0], batch):
        chunk = images[start : start + batch]
        if hasattr(segmenter, "predict_maps"):
            m = segmenter.predict_maps(chunk, entropy=True, **{k: True for k in sorted(needs)})
            got = (m.labels, m.confidence, m.entropy, m.energy, m.gram)
        else:  # a stand-in with only predict_with_entropy (the tests' fixed segmenters): host tensors
            lab, c, e = segmenter.predict_with_entropy(chunk.numpy() if isinstance(chunk, torch.Tensor) else chunk)
            got = (torch.as_tensor(lab).to(torch.uint8), torch.as_tensor(c), torch.as_tensor(e), None, None)
        for k, v in zip(names, got):
            parts[k].append(v)
    cat = (lambda xs: None if any(x is None for x in xs) else xs[0] if len(xs) == 1 else torch.cat(xs, dim=0))
    return {k: cat(v) for k, v in parts.items()}


class GroupJob:
    """One group's reductions, launched on the device: each registered metric's `update` on the shared
    `GroupContext`, all copied to the host at once; `result()` reads them on the host (waiting, on a GPU, only
    for this group's copies) and writes the dict `group_counts` returns, one field per metric."""

    def __init__(self, item: dict[str, Any], inputs: dict[str, Any], segmenter: Any, s: dict[str, Any],
                 use_pl: bool, batch: int, model: str, dataset_name: str) -> None:
        self.item, self.s, self.use_pl, self.model, self.dataset_name = item, s, use_pl, model, dataset_name
        self.metrics = registry.metrics()
        present = item["present"]
        self.clean = present.index(s["clean"])
        self.has_target = inputs["has_target"]
        self.has_gt = inputs["gt"] is not None
        with torch.inference_mode():
            _use(inputs)
            maps = _maps(segmenter, inputs["images"], batch, {n for m in self.metrics for n in m.needs})
            labels = maps["labels"]
            on = (lambda t: None if t is None else t.to(labels.device))  # there already, but for a stand-in model
            ctx = GroupContext(labels, maps["confidence"], maps["entropy"], self.clean, on(inputs["pseudo"]),
                               on(inputs["targets"]), on(inputs["visible"]), s["tau_mass"], on(inputs["gt"]), use_pl,
                               energy=maps["energy"], gram=maps["gram"])
            out = {f"{n}/{k}": v for n, m in enumerate(self.metrics) for k, v in m.update(ctx).items()}
            out["pred"] = labels
            out["conf"] = confidence_thumbnail(maps["confidence"])
            self.copy = reductions.HostCopy(out)

    def result(self) -> dict[str, Any]:
        r = self.copy.get()
        present = self.item["present"]
        pred, conf = r.pop("pred"), r.pop("conf")
        group = Group(self.item["group_id"], list(present), self.clean, [bool(t) for t in self.has_target],
                      self.has_gt, self.use_pl, tuple(pred.shape[1:]), self.model, self.dataset_name, self.s)
        own: list[dict[str, np.ndarray]] = [{} for _ in self.metrics]
        for key, v in r.items():
            n, name = key.split("/", 1)
            own[int(n)][name] = v
        out: dict[str, Any] = {"group_id": self.item["group_id"]}
        for m, host in zip(self.metrics, own):
            out[m.key] = m.record(host, group)
        # own memory: the pinned buffer goes back
        out["pred"] = {c: np.array(pred[i], dtype=np.uint8) for i, c in enumerate(present)}
        out["conf"] = {c: np.array(conf[i], dtype=np.uint8) for i, c in enumerate(present)}
        return out


def confidence_thumbnail(confidence: Any) -> Any:
    """N x H x W max probabilities -> N x ceil(H/s) x ceil(W/s) uint8 (0-255 for 0-1), s = entry.CONFIDENCE_STEP: what
    the qualitative figure shows (at a sixth of the page's width), stored so that no figure predicts again."""
    step = entry.CONFIDENCE_STEP
    c = torch.nan_to_num(confidence.float(), nan=0.0)[:, None]
    pooled = F.avg_pool2d(c, step, ceil_mode=True, count_include_pad=False)[:, 0] if step > 1 else c[:, 0]
    return pooled.clamp(0, 1).mul(255).round().to(torch.uint8)


def launch_group(item: dict[str, Any], segmenter: Any, s: dict[str, Any], reference: str, use_pl: bool, batch: int,
                 model: str, dataset_name: str, inputs: dict[str, Any] | None = None) -> GroupJob:
    """Start one group's forward and reductions (`item` from `GroupInputs`, packed or not; `inputs` its tensors
    already on the device, from `stage_inputs`)."""
    if inputs is None:
        packed = item["packed"] if "packed" in item else pack_group(item, reference)["packed"]
        inputs = stage_inputs(packed, _device(segmenter))
    return GroupJob(item, inputs, segmenter, s, use_pl, batch, model, dataset_name)


def group_counts(item: dict[str, Any], segmenter: Any, s: dict[str, Any], reference: str, use_pl: bool,
                 batch: int, model: str, dataset_name: str) -> dict[str, Any]:
    """Everything evaluate keeps of one group (`item` from `GroupInputs`): per registered metric its record under
    its `key` (`xi` per "<source>|<condition>" the retained and reference pixels per class, `cm` per condition the
    confusion matrix against its ground truth, `agreement` and `counts` (phi) rows, `estimators` sums, ...) and
    `pred` the label maps."""
    return launch_group(item, segmenter, s, reference, use_pl, batch, model, dataset_name).result()


def estimator_sums(pred: Any, conf: Any, entropy: Any, clean_pred: Any) -> dict[str, Any]:
    """What the label-free estimators of accuracy under shift need of one image, as sums over all its pixels
    (no labels, no confidence filter): pixel count, summed max probability (AC, DoC), summed normalised
    entropy, the max-probability histogram (ATC) and the pixels predicted as on the clean image (plain
    agreement). Sums, so that groups add up and the bootstrap resamples them. (One image through the same
    reductions evaluate runs on the device.)"""
    p, c, e, q = (torch.as_tensor(np.asarray(x))[None] for x in (pred, conf, entropy, clean_pred))
    return {"pixels": int(p[0].numel()), "conf_sum": reductions.image_sums(c)[0],
            "entropy_sum": reductions.image_sums(e)[0], "conf_hist": reductions.confidence_histogram(c)[0].tolist(),
            "agree_clean": int((p == q).sum())}


@contextmanager
def frozen_heap() -> Iterator[None]:
    """The objects alive before the counting loop (the app, the model, the earlier stages' garbage) left out of
    the garbage collector's passes until it ends: a full pass over them, due by chance inside the loop, stalled
    a few of its groups by a tenth of a second each (one stage run of three in experiments/bench_evaluate.py).
    Objects made inside the loop are collected as ever; the frozen ones go back to the collector on exit."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def count_groups(dataset: PairedDataset, labels: LabelMaps, segmenter: Any, s: dict[str, Any], conditions: list[str],
                 groups: list[Any], batch: int, workers: int, maps: Any = None) -> list[dict[str, Any]]:
    """`group_counts` of `groups` (those with the clean image), under the metric settings `s`, images
    decoded by `workers` DataLoader workers. Launches group g before reading group g-1's results, so a GPU
    always has a group queued; the finite-output check is read once, at the end. `maps`: called with each
    group's id, label maps and max probabilities as they come (entry.PredictionWriter.add), which then leave
    the results (else they stay in them)."""
    clean = s["clean"]
    order = [clean] + [c for c in conditions if c != clean]
    use_pl = s["reference_mode"] in ("pseudo_label", "both")
    use_gt = s["reference_mode"] in ("ground_truth", "both")
    device = _device(segmenter)
    inputs = GroupInputs(dataset, groups, order, clean, labels, use_gt, s["sampling"], s["sampling_seed"],
                         s["min_transmittance"], packed=True)
    results: list[dict[str, Any]] = []
    waiting: GroupJob | None = None
    staged = None
    loader = iter(tqdm(load_groups(inputs, workers, pin_memory=device.type == "cuda"), total=len(groups),
                       desc=f"evaluate [{segmenter.name}]", unit="group"))

    def next_staged() -> Any:
        for item in loader:
            if "error" in item:
                raise DataError(item["error"])
            if item["present"]:
                return item, stage_inputs(item["packed"], device)
        return None

    def finish(job: GroupJob) -> dict[str, Any]:
        r = job.result()
        if maps is not None:
            maps(r["group_id"], r.pop("pred"), r.pop("conf"))
        return r

    with frozen_heap():
        staged = next_staged()
        while staged is not None:
            item, on_device = staged
            job = GroupJob(item, on_device, segmenter, s, use_pl, batch, segmenter.name, dataset.name)
            if waiting is not None:
                results.append(finish(waiting))
            waiting = job
            staged = next_staged()  # decoded while the device computes; copied on the side stream
        if waiting is not None:
            results.append(finish(waiting))
    check = getattr(segmenter, "check_finite", None)
    if check is not None:
        check()
    return results


__all__ = ["PSEUDO_LABEL", "GT", "CONF_BINS", "group_counts", "launch_group", "estimator_sums", "count_groups",
           "stage_inputs", "GroupJob"]
