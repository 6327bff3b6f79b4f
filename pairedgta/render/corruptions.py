"""Writing the corruption conditions' images (pairedgta/corruptions.py): a rendered scene's, in the worker that
rendered it (generate), and an existing dataset's groups (dataset.root: the released PairedGTA layout), over worker
processes. Each group lands under a temporary name and is renamed when complete, so a crash resumes."""
from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing as mp
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pairedgta import corruptions
from pairedgta.conditions import ConditionGrid
from pairedgta.datasets.base import save_png_atomic
from pairedgta.datasets.generated import scene_files
from pairedgta.errors import PairedGTAError
from pairedgta.jsonio import write_json

log = logging.getLogger("pairedgta.generate")


def corrupt_scene(scene_dir: Path, scene_id: str, images: dict[str, np.ndarray], grid: ConditionGrid,
                  seed: int) -> None:
    """Write each corruption condition's image: its clean image through the library, seeded by (seed, scene,
    condition). No label, instance or transmittance file: the readers give it the clean condition's truth."""
    for c in grid.corrupted:
        seeded = corruptions.seed_for(seed, scene_id, c.name)
        image = corruptions.corrupt(images[c.source], c.corruption, c.severity, seeded)
        save_png_atomic(image, scene_files(scene_dir, c.name)[0])


def writer_alive(tmp: Path) -> bool:
    """Whether the process that names `.tmp-<scene>-<pid>` still runs (on this machine)."""
    try:
        pid = int(tmp.name.rsplit("-", 1)[1])
    except (IndexError, ValueError):
        return False
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


DONE = "done.json"  # a group's corrupted images are complete (written last)


def corrupt_group(group: Any, grid: ConditionGrid, seed: int, scenes_dir: Path) -> None:
    """The corruption conditions of one group of an existing dataset, from its clean image (which stays where it is),
    into scenes_dir/<group id>/ under a temporary name, renamed when complete."""
    from pairedgta.datasets import load_image

    final = scenes_dir / str(group.group_id)
    tmp = scenes_dir / f".tmp-{group.group_id}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        sources = {c.source for c in grid.corrupted}
        images = {c: load_image(group.images[c]) for c in sources if c in group.images}
        missing = sorted(sources - set(images))
        if missing:
            raise PairedGTAError(f"group {group.group_id}: no image of {', '.join(missing)} to corrupt; set "
                                 "conditions.corruptions.of to a condition every group has (the reference)")
        t0 = time.perf_counter()
        corrupt_scene(tmp, str(group.group_id), images, grid, seed)
        write_json(tmp / DONE, {"group_id": str(group.group_id), "corruption_time": time.perf_counter() - t0})
        if final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


_CORRUPT: dict[str, Any] = {}


def _init_corrupt_worker(groups: list[Any], grid: ConditionGrid, seed: int) -> None:
    _CORRUPT.update(groups={str(g.group_id): g for g in groups}, grid=grid, seed=seed)


def _corrupt_work(group_id: str, scenes_dir: str) -> None:
    w = _CORRUPT
    corrupt_group(w["groups"][group_id], w["grid"], w["seed"], Path(scenes_dir))


def corrupt_groups(dataset: Any, grid: ConditionGrid, gen: Any, out: Path, indices: list[int]) -> None:
    """The groups `indices` of `dataset` not yet corrupted in out/scenes, over generate.workers processes."""
    corruptions.library()
    scenes_dir = out / "scenes"
    scenes_dir.mkdir(parents=True, exist_ok=True)
    for tmp in scenes_dir.glob(".tmp-*"):
        if not writer_alive(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    groups = [dataset.groups[i] for i in indices if not (scenes_dir / str(dataset.groups[i].group_id) / DONE).is_file()]
    if len(groups) < len(indices):
        log.info("corruptions: resuming, %d of %d groups already corrupted", len(indices) - len(groups), len(indices))
    if gen.workers == 1:
        for g in tqdm(groups, desc="corruptions", unit="group"):
            corrupt_group(g, grid, gen.seed, scenes_dir)
        return
    ctx = mp.get_context("spawn")
    with cf.ProcessPoolExecutor(gen.workers, mp_context=ctx, initializer=_init_corrupt_worker,
                                initargs=(groups, grid, gen.seed)) as pool:
        futures = [pool.submit(_corrupt_work, str(g.group_id), str(scenes_dir)) for g in groups]
        for fut in tqdm(cf.as_completed(futures), total=len(futures), desc="corruptions", unit="group"):
            fut.result()
