"""What evaluate reads of one group: the conditions it evaluates (all, or the authors' random draw) and
their images, label maps and visibility masks, decoded in DataLoader workers so that the model forward,
not PNG decoding, bounds evaluation."""
from __future__ import annotations

import functools
import os
import zlib
from typing import Any

import numpy as np

from pairedgta.cityscapes import IGNORE_INDEX
from pairedgta.datasets import LabelMaps, PairedDataset, load_group_images, load_label, load_transmittance
from pairedgta.datasets.base import NOTES_ENV
from pairedgta.errors import DataError, PairedGTAError
from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

def sampled_conditions(group_id: str, present: list[str], clean: str, sampling: str, seed: int) -> list[str]:
    """The conditions of one group to evaluate: all, or the clean one plus one adverse condition drawn
    as the authors' loader draws it: a time of day uniformly (the part of the name before the first
    "-": Day, Sunset, Night), then one of that time's adverse weathers uniformly. On the paper's grid a
    Day condition is drawn for 1/3 of the groups, not 2/8. The draw depends only on (seed, group id), so
    it is reproducible and does not change when groups are added, reordered or split over shards."""
    if sampling == "all":
        return present
    adverse = [c for c in present if c != clean]
    if not adverse:
        return present
    by_time: dict[str, list[str]] = {}
    for c in adverse:
        by_time.setdefault(c.split("-", 1)[0], []).append(c)
    rng = np.random.default_rng([seed, zlib.crc32(str(group_id).encode())])
    weathers = list(by_time.values())[int(rng.integers(len(by_time)))]
    return [clean, weathers[int(rng.integers(len(weathers)))]]


class GroupInputs:  # a map-style dataset for torch's DataLoader (__len__ + __getitem__)
    """Decodes one group's images and label maps, in DataLoader workers (`evaluate.num_workers`). Errors
    come back as values, so the main process raises the same one-line error a sequential run would."""

    def __init__(self, dataset: PairedDataset, groups: list[Any], order: list[str], clean: str,
                 labels: LabelMaps, use_gt: bool, sampling: str = "all", sampling_seed: int = 0,
                 min_transmittance: float = 0.0, packed: bool = False) -> None:
        self.dataset, self.groups, self.order, self.clean = dataset, groups, order, clean
        self.labels, self.use_gt = labels, use_gt
        self.sampling, self.sampling_seed = sampling, sampling_seed
        self.min_transmittance = min_transmittance
        self.packed = packed  # hand the group over as `pack_group` tensors (stacked where it was decoded)

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, i: int) -> dict[str, Any]:
        try:
            item = self._load(self.groups[i])
            return pack_group(item, self.dataset.reference) if self.packed and item["present"] else item
        except PairedGTAError as exc:
            return {"error": str(exc), "kind": type(exc).__name__}

    def _load(self, group: Any) -> dict[str, Any]:
        present = [c for c in self.order if c in group.images]
        if self.clean not in present:
            return {"group_id": group.group_id, "present": []}
        present = sampled_conditions(group.group_id, present, self.clean, self.sampling, self.sampling_seed)
        images = load_group_images(group, present)
        shape = images[self.clean].shape[:2]
        pl_path = self.labels.path(group.group_id)
        pseudo = load_label(pl_path)
        if pseudo.shape != shape:
            raise DataError(
                f"{pl_path}: pseudo-label is {pseudo.shape[1]}x{pseudo.shape[0]} but the images of group "
                f"{group.group_id} are {shape[1]}x{shape[0]}; rerun with force=[pseudolabel]"
            )
        own: dict[str, np.ndarray] = {}
        for c in present if self.use_gt else []:
            if c in group.labels:
                own[c] = load_label(group.labels[c])
                if own[c].shape != shape:
                    raise DataError(f"{group.labels[c]}: label map size differs from its image")
        return {"group_id": group.group_id, "present": present, "images": images, "pseudo": pseudo, "own": own,
                "visible": self._visible(group, present, shape)}

    def _visible(self, group: Any, present: list[str], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
        """metric.min_transmittance > 0: per condition, the pixels visible in it and in the clean image."""
        if self.min_transmittance <= 0.0:
            return {}
        seen: dict[str, np.ndarray] = {}
        for c in present:
            if c not in group.transmittance:
                raise DataError(f"group {group.group_id} of {self.dataset.root} has no transmittance map for {c}; "
                                "regenerate it with renderer=blender or synthetic, or set metric.min_transmittance=0")
            t = load_transmittance(group.transmittance[c])
            if t.shape != shape:
                raise DataError(f"{group.transmittance[c]}: transmittance map size differs from its image")
            seen[c] = t >= self.min_transmittance
        return {c: seen[c] & seen[self.clean] for c in present}


def pack_group(item: dict[str, Any], reference: str) -> dict[str, Any]:
    """One group's inputs as the few tensors its reductions take, in the order of `item["present"]`: `images`
    N x H x W x 3 uint8; `pseudo` H x W; `targets` N x H x W, each condition's ground truth for its IoU (its own
    labels, else the reference's; 255 where it has none, `has_target` says which); `gt` the reference's truth
    for xi (or None); `visible` N x H x W bool (or None). Torch tensors: from DataLoader workers they travel
    through shared memory, not a pickle, and can be pinned for a non-blocking copy to the GPU."""
    present, own = item["present"], item.get("own") or {}
    images = item["images"]
    first = np.asarray(images[present[0]])
    # numpy builds them (no torch kernel: this may run in a decoding thread beside the forward's thread pool)
    stack = np.empty((len(present), *first.shape), dtype=np.uint8)
    for i, c in enumerate(present):
        stack[i] = images[c]
    gt = own.get(reference)
    has_target = [c in own or gt is not None for c in present]
    targets = None
    if any(has_target):
        targets = np.full((len(present), *first.shape[:2]), IGNORE_INDEX, dtype=np.uint8)
        for i, c in enumerate(present):
            label = own[c] if c in own else gt
            if label is not None:
                targets[i] = label
    seen = item.get("visible") or {}
    visible = np.stack([np.asarray(seen[c], dtype=bool) for c in present]) if seen else None
    tensor = (lambda a: None if a is None else torch.from_numpy(a))
    return {"group_id": item["group_id"], "present": present, "packed": {
        "images": tensor(stack), "pseudo": tensor(np.array(item["pseudo"], dtype=np.uint8)),
        "targets": tensor(targets), "has_target": has_target,
        "gt": None if gt is None else tensor(np.array(gt, dtype=np.uint8)), "visible": tensor(visible)}}


def _identity(item: Any) -> Any:
    return item


# what a decoding worker imports before it unpickles its dataset: loaded once, in the fork server
WORKER_PRELOAD = ("torch", "pairedgta.evaluation.inputs")


def worker_context() -> Any:
    """How decoding workers start: forked from a small server process (multiprocessing's forkserver), not from
    this one. A worker forked from the stage's own process shares its heap copy-on-write, and the stage reuses
    its freed memory (models.runtime.reuse_freed_memory): every page the forward then writes was copied first, a
    fault each, which made the forward 30 % slower at 2 workers on the CPU. The server imports torch and this
    module once, so a worker starts in milliseconds. None (the platform's default) where there is no fork server."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return None
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(WORKER_PRELOAD))  # read when the server starts; a running one is kept
    return ctx


def start_workers_server(workers: int) -> None:
    """Starts the decoding workers' server now, when `workers` > 0, so that it imports torch while the stage builds
    its model, not when the first group is wanted; a no-op once it runs."""
    ctx = worker_context() if workers > 0 else None
    if ctx is not None:
        from multiprocessing import forkserver

        forkserver.ensure_running()


def _notes_into(path: str | None, worker_id: int) -> None:
    """A decoding worker's image notes go where the run's open scope collects them (datasets.base.image_notes):
    the fork server, and so every worker, has the environment of the moment it started, which may be before
    the scope (an earlier stage or run of the process), so the path travels with the DataLoader."""
    if path is None:
        os.environ.pop(NOTES_ENV, None)
    else:
        os.environ[NOTES_ENV] = path


def load_groups(inputs: GroupInputs, workers: int, pin_memory: bool = False) -> Any:
    """The groups' inputs in order: decoded in this process (workers=0) or by `workers` DataLoader workers
    (`worker_context`); with `pin_memory` (a GPU) their tensors arrive in pinned memory, ready for a non-blocking
    copy."""
    if workers < 1:  # not a thread either: beside the forward's OpenMP threads it slowed the forward down (2 cores)
        return (inputs[i] for i in range(len(inputs)))
    return torch.utils.data.DataLoader(inputs, batch_size=None, shuffle=False, num_workers=workers,
                                       collate_fn=_identity, prefetch_factor=2, persistent_workers=False,
                                       pin_memory=pin_memory, multiprocessing_context=worker_context(),
                                       worker_init_fn=functools.partial(_notes_into, os.environ.get(NOTES_ENV)))
