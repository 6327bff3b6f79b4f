"""Generate stage, Algorithm 1 of the paper: per scene, sample a location, build the descriptor with
dynamic objects, then render it under every condition. Resumable: each finished scene is renamed into
the stage's partial directory, so a rerun after a crash keeps it and continues.

Pairing hook (`generate.pairing`): by default every condition is rendered from the one SceneDescriptor
(perfect pairing). Non-zero `camera_jitter_m`, `camera_jitter_deg`, `object_resample_prob` or
`object_move_m` perturb the descriptor once per adverse condition (camera offset and rotation, objects
re-drawn in R_k or moved), emulating coarsely paired real data such as ACDC; the reference condition
always uses the unperturbed descriptor. The perturbation acts on the descriptor only, so it works with
every renderer; it is seeded by (scene seed, condition name) and enters the stage hash."""
from __future__ import annotations

import concurrent.futures as cf
import csv
import json
import logging
import multiprocessing as mp
import os
import shutil
import time
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from pairedgta import corruptions
from pairedgta.conditions import ConditionGrid, build_condition_grid
from pairedgta.datasets.base import save_png_atomic
from pairedgta.datasets.generated import INDEX, boxes_file, scene_files, transmittance_file, transmittance_png
from pairedgta.errors import ConfigError, PairedGTAError, RendererError, reason
from pairedgta.jsonio import write_json
from pairedgta.render import Renderer, build_renderer, renderer_versions
from pairedgta.render.corruptions import corrupt_scene, writer_alive
from pairedgta.scene.descriptor import CameraPose, DynamicObject, SceneDescriptor
from pairedgta.scene.placement import PlacementConfig, place_objects
from pairedgta.scene.sampling import build_region, region_for_scene
from pairedgta.cache import SHARED_WORK
from pairedgta.schema import GenerateConfig, PairingConfig, RunConfig, ValidationConfig, as_dict
from pairedgta.stages.common import Context, StageResult, run_cached, stage_key

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

log = logging.getLogger("pairedgta.generate")
VERSION = "7"  # 2: descriptors carry the ambient population; 3: per-town ground materials;
# 4: signs along every street, board and railing fences, garden walls, guard railings;
# 5: analytic fog by default, and clear skies lit by the sun (the fog box no longer shadows it);
# 6: conditions in physical units (visibility, rain rate) and a transmittance map per condition;
# 7: the camera model (`camera` group), night light at realistic power, haze that replaces the sky
# (the renderer's own version, e.g. blender_version, is part of the key beside VERSION: hash_config)
TIMING_COLUMNS = [
    "location_id", "scene_id", "x", "y", "scene_sampling_time", "semantic_scene_construction_time",
    "condition_wise_rendering_time", "pipeline_time", "overhead_time", "total_time", "retries",
]
EXECUTION_KEYS = ("workers", "endpoints", "num_shards", "shard")  # where scenes run, not what they are
# how to reach and retry the renderer, not what it renders: left out of the dataset hash
RENDERER_EXECUTION_KEYS = ("host", "port", "timeout_s", "retries", "backoff_s")


class GeneratedData(StageResult):
    """The generate stage's entry: the dataset (read through pairedgta.datasets) plus its run records.
    `complete` is False for a shard job that left scenes to other shards (nothing to read yet)."""

    @property
    def timings_csv(self) -> Path:
        return self.path / "timings.csv"

    def validation(self) -> Any:  # pandas.DataFrame | None (pandas imported on use)
        import pandas as pd

        path = self.path / "validation.csv"
        return pd.read_csv(path, dtype={"scene_id": str}) if path.is_file() else None


def is_perfect(pairing: PairingConfig) -> bool:
    return all(v == 0 for v in as_dict(pairing).values())


def placement(gen: GenerateConfig) -> PlacementConfig:
    return PlacementConfig.from_cfg(as_dict(gen.objects))


def perturb_descriptor(
    descriptor: SceneDescriptor, condition: str, pairing: PairingConfig, placement: PlacementConfig, region: Any
) -> SceneDescriptor:
    """The scene as a coarse pair would show it under `condition`: the camera offset by up to
    camera_jitter_m per axis and rotated by up to camera_jitter_deg per axis (uniform), each object
    re-drawn in R_k with probability object_resample_prob (dropped if R_k has no room within d_min),
    else moved by up to object_move_m. Static geometry (seed, scene id, location) is kept."""
    rng = np.random.default_rng(np.random.SeedSequence([descriptor.seed, zlib.crc32(condition.encode())]))
    jm, jd = pairing.camera_jitter_m, pairing.camera_jitter_deg
    cam = descriptor.camera
    dx, dy, dz = rng.uniform(-jm, jm, size=3) if jm > 0 else (0.0, 0.0, 0.0)
    rx, ry, rz = rng.uniform(-jd, jd, size=3) if jd > 0 else (0.0, 0.0, 0.0)
    camera = replace(
        cam, x=round(cam.x + dx, 4), y=round(cam.y + dy, 4), z=round(max(0.3, cam.z + dz), 4),
        rot_x=round(cam.rot_x + rx, 4), rot_y=round(cam.rot_y + ry, 4), rot_z=round(cam.rot_z + rz, 4),
    )
    kept: list[DynamicObject] = []
    redraw: list[int] = []
    for i, obj in enumerate(descriptor.objects):
        if pairing.object_resample_prob > 0 and rng.random() < pairing.object_resample_prob:
            redraw.append(i)
            continue
        m = pairing.object_move_m
        if m > 0:
            df, dr = rng.uniform(-m, m, size=2)
            obj = replace(obj, forward=round(obj.forward + df, 3), right=round(obj.right + dr, 3))
        kept.append(obj)
    one = replace(placement, min=1, max=1)
    for _ in redraw:
        for _try in range(20):
            new, _ = place_objects(rng, descriptor.location, region, one)
            if new and all((new[0].forward - o.forward) ** 2 + (new[0].right - o.right) ** 2 >= placement.d_min**2 for o in kept):
                kept.append(new[0])
                break
    extra = dict(descriptor.extra)
    extra["pairing"] = {"condition": condition, **as_dict(pairing)}
    return replace(descriptor, camera=camera, objects=tuple(kept), extra=tuple(sorted(extra.items())))


def hash_config(run: RunConfig, grid: ConditionGrid) -> dict[str, Any]:
    gen = {k: v for k, v in as_dict(run.generate).items() if k not in EXECUTION_KEYS}
    pairing = gen.pop("pairing")
    if not is_perfect(run.generate.pairing):  # perfect pairing hashes as before the hook existed
        gen["pairing"] = pairing
    renderer = {k: v for k, v in run.renderer.items() if k not in RENDERER_EXECUTION_KEYS}
    return {
        "generate": gen, "renderer": renderer, "region": run.region,
        "conditions": [c.to_dict() for c in grid], "reference": grid.reference,
        # the backend's own version (blender_version): another Blender draws other pixels, so another entry; the
        # manifest's config records it. A backend without one (synthetic, deepgtav) hashes as before
        **renderer_versions(run.renderer.get("backend")),
        # a set with corruption conditions: the library and its version (another version, other pixels); none else
        **corruptions.hash_config(grid),
    }


def scene_seed(base_seed: int, k: int) -> int:
    """Per-scene seed from (base seed, scene index) only, so scenes are the same whatever the sharding."""
    return int(np.random.SeedSequence([int(base_seed), int(k)]).generate_state(1)[0])


def build_descriptor(k: int, gen: GenerateConfig, region: Any) -> tuple[SceneDescriptor, dict[str, float]]:
    region = region_for_scene(region, k)
    seed = scene_seed(gen.seed, k)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    location = region.sample_location(rng)
    t1 = time.perf_counter()
    objects, requested = place_objects(rng, location, region, placement(gen))
    camera = CameraPose(**as_dict(gen.camera))
    descriptor = SceneDescriptor(
        scene_id=f"{k:05d}", seed=seed, location=location, camera=camera, objects=objects,
        region=getattr(region, "name", ""), requested_objects=requested,
        # regions with a generated layout store it, so the descriptor alone replays the scene
        extra=(("town", region.params()),) if hasattr(region, "params") else (),
    )
    if hasattr(region, "populate"):  # the region's ambient traffic and pedestrians, kept clear of the objects
        descriptor = region.populate(descriptor)
    if len(objects) < requested:
        log.info("scene %s: placed %d of %d objects (region R_k too small for d_min)", descriptor.scene_id, len(objects), requested)
    return descriptor, {"scene_sampling_time": t1 - t0, "descriptor_time": time.perf_counter() - t1}


def render_scene(
    k: int, gen: GenerateConfig, grid: ConditionGrid, renderer: Renderer, region: Any, scenes_dir: Path
) -> dict[str, Any]:
    """Render scene k into scenes_dir/<id> atomically; returns its timing row."""
    descriptor, t = build_descriptor(k, gen, region)
    region = region_for_scene(region, k)
    final = scenes_dir / descriptor.scene_id
    tmp = scenes_dir / f".tmp-{descriptor.scene_id}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        t0 = time.perf_counter()
        renderer.prepare(descriptor)
        construction = t["descriptor_time"] + time.perf_counter() - t0
        t1 = time.perf_counter()
        states: dict[str, dict] = {}
        images: dict[str, np.ndarray] = {}
        pairing = gen.pairing
        perturbed: dict[str, SceneDescriptor] = {}
        for condition in grid.rendered:
            shown = descriptor
            if condition.name != grid.reference and not is_perfect(pairing):
                shown = perturb_descriptor(descriptor, condition.name, pairing, placement(gen), region)
                perturbed[condition.name] = shown
                shown.save(tmp / f"{condition.name}_descriptor.json")
            result = renderer.render(shown, condition)
            if result.image.shape[:2] != (renderer.height, renderer.width):
                raise RendererError(
                    f"renderer returned {result.image.shape[1]}x{result.image.shape[0]} for "
                    f"renderer.width x height = {renderer.width}x{renderer.height}"
                )
            img_path, lab_path, inst_path = scene_files(tmp, condition.name)
            save_png_atomic(result.image, img_path)
            if result.distance is not None:  # what the air hides: metric.min_transmittance scores only the rest
                save_png_atomic(transmittance_png(condition.transmittance(result.distance)),
                                transmittance_file(tmp, condition.name))
            if result.labels is not None:
                save_png_atomic(result.labels.astype(np.uint8), lab_path)
            if result.instances is not None:
                save_png_atomic(result.instances.astype(np.uint16), inst_path)
            elif result.boxes is not None:  # the backend's own 2D boxes where it gives no instance ids (DeepGTAV)
                write_json(boxes_file(tmp, condition.name), {"boxes": result.boxes})
            states[condition.name] = result.state
            images[condition.name] = result.image
        t2 = time.perf_counter()
        corrupt_scene(tmp, descriptor.scene_id, images, grid, gen.seed)
        corrupting = time.perf_counter() - t2
        rendering = time.perf_counter() - t1
        # the rendered images only: a corrupted one is paired by construction, and a strong filter (glass blur 5)
        # would fail the structure check that looks for a renderer that moved something
        validation = validate(images, grid, descriptor, states, gen.validation, perturbed)
        descriptor.save(tmp / "descriptor.json")
        # the backend's overhead (reconnects, retries, waiting) happens inside the phases; the paper
        # reports it apart from the pipeline time, so it is moved out of the phases here
        overhead = float(getattr(renderer, "overhead_s", 0.0))
        wall = t["scene_sampling_time"] + construction + rendering
        row = {
            "location_id": k, "scene_id": descriptor.scene_id, "x": descriptor.location.x, "y": descriptor.location.y,
            "scene_sampling_time": t["scene_sampling_time"], "semantic_scene_construction_time": construction,
            "condition_wise_rendering_time": rendering, "pipeline_time": max(wall - overhead, 0.0),
            "overhead_time": overhead, "total_time": wall, "retries": int(getattr(renderer, "retries_used", 0)),
            **({"corruption_time": corrupting} if grid.corrupted else {}),
        }
        write_json(tmp / "timings.json", row)
        write_json(tmp / "validation.json", validation)
        if final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
        return row
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def validators() -> tuple[Any, Any]:
    """(validate_group, entity_mismatches) of pairedgta.scene.validation. A module that fails to import
    is a broken install: one line naming what is missing and the fix, never a scene passed unchecked."""
    try:
        from pairedgta.scene.validation import entity_mismatches, validate_group
    except ImportError as exc:
        package = exc.name and exc.name.split(".")[0] != "pairedgta"
        what = f"the Python package '{exc.name}' is not installed" if package else "pairedgta.scene.validation is broken"
        raise PairedGTAError(
            f"generate: pair validation cannot run: {what} ({reason(exc)}); reinstall pairedgta (pip install -e . "
            "in the project), or set generate.validation.enabled=false to render without pair validation"
        ) from None
    return validate_group, entity_mismatches


def validate(images, grid, descriptor, states, vcfg: ValidationConfig, perturbed=None) -> dict[str, Any]:
    if not vcfg.enabled:
        return {"ok": True, "reasons": [], "structure": {}}
    validate_group, entity_mismatches = validators()  # a broken install fails, never passes

    perturbed = perturbed or {}
    res = validate_group(
        images, grid.reference, descriptor=descriptor,
        states={c: s for c, s in states.items() if c not in perturbed},
        threshold=vcfg.structure_threshold,
    )
    reasons = list(res.reasons)
    # a deliberately perturbed condition is checked against the descriptor it was rendered from
    for cond, shown in perturbed.items():
        reasons += [f"{cond}: {why}" for why in entity_mismatches(shown, states.get(cond) or {})]
    return {"ok": not reasons, "reasons": reasons, "structure": dict(res.structure)}


# -- worker processes for generate.workers > 1 -------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(run: RunConfig, endpoints: Any) -> None:
    renderer_cfg = dict(run.renderer)
    if endpoints is not None:
        endpoint = endpoints.get()
        renderer_cfg.update(endpoint)
    grid = build_condition_grid(run.conditions)
    renderer = build_renderer(renderer_cfg)
    renderer.open()
    _WORKER.update(gen=run.generate, grid=grid, renderer=renderer, region=build_region(run.region))


def _work(k: int, scenes_dir: str) -> dict[str, Any]:
    w = _WORKER
    return render_scene(k, w["gen"], w["grid"], w["renderer"], w["region"], Path(scenes_dir))


def finished_scenes(scenes_dir: Path) -> set[int]:
    if not scenes_dir.is_dir():
        return set()
    return {int(p.name) for p in scenes_dir.iterdir() if p.is_dir() and p.name.isdigit() and (p / "timings.json").is_file()}


def render_scenes(run: RunConfig, grid: ConditionGrid, out: Path, indices: list[int]) -> float:
    """Render the scenes `indices` that are not yet in out/scenes; returns the backend's connect time."""
    gen = run.generate
    n = len(indices)
    workers = gen.workers
    if gen.validation.enabled:
        validators()  # a broken install says so before the first scene is rendered, not after it
    if grid.corrupted:
        corruptions.library()  # likewise the corruption library
    scenes_dir = out / "scenes"
    scenes_dir.mkdir(parents=True, exist_ok=True)
    for tmp in scenes_dir.glob(".tmp-*"):
        if not writer_alive(tmp):  # a crashed job's half scene; a live shard's is left alone
            shutil.rmtree(tmp, ignore_errors=True)
    done = finished_scenes(scenes_dir)
    todo = [k for k in indices if k not in done]
    if len(todo) < n:
        log.info("generate: resuming, %d of %d scenes already rendered", n - len(todo), n)
    region = build_region(run.region)
    if hasattr(region, "order"):
        todo = region.order(todo)
    t_open = time.perf_counter()
    if workers == 1:
        renderer = build_renderer(dict(run.renderer))
        renderer.open()
        connect = time.perf_counter() - t_open
        try:
            for k in tqdm(todo, desc="generate", unit="scene"):
                render_scene(k, gen, grid, renderer, region, scenes_dir)
        finally:
            renderer.close()
    else:
        endpoints = gen.endpoints
        ctx = mp.get_context("spawn")
        queue = None
        if endpoints:
            if len(endpoints) < workers:
                raise ConfigError(
                    f"generate.workers={workers} but generate.endpoints lists {len(endpoints)}; give one per worker"
                )
            queue = ctx.Manager().Queue()
            for e in endpoints[:workers]:
                queue.put(as_dict(e))
        with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(run, queue)) as pool:
            futures = [pool.submit(_work, k, str(scenes_dir)) for k in todo]
            for fut in tqdm(cf.as_completed(futures), total=len(futures), desc="generate", unit="scene"):
                fut.result()
        connect = 0.0
    return connect


def generate_dataset(run: RunConfig, grid: ConditionGrid, out: Path) -> dict[str, Any]:
    n = run.generate.num_scenes
    connect = render_scenes(run, grid, out, list(range(n)))
    (out / SHARED_WORK).unlink(missing_ok=True)  # complete: no shard writes here any more
    return write_index(out, run, grid, n, connect)


def write_index(out: Path, run: RunConfig, grid: ConditionGrid, n: int, connect: float) -> dict[str, Any]:
    scenes_dir = out / "scenes"
    rows, valid_rows, scenes = [], [], []
    drop_invalid = run.generate.drop_invalid
    for k in range(n):
        sdir = scenes_dir / f"{k:05d}"
        row = json.loads((sdir / "timings.json").read_text())
        rows.append(row)
        v = json.loads((sdir / "validation.json").read_text())
        valid_rows.append({"scene_id": sdir.name, "ok": v["ok"], "reasons": "; ".join(v["reasons"]),
                           **{f"structure/{c}": s for c, s in v["structure"].items()}})
        if v["ok"] or not drop_invalid:
            scenes.append({"scene_id": sdir.name, "dir": f"scenes/{sdir.name}"})
    if rows:
        rows[0]["overhead_time"] += connect
        rows[0]["total_time"] += connect
    _write_csv(out / "timings.csv", rows, TIMING_COLUMNS + (["corruption_time"] if grid.corrupted else []))
    _write_csv(out / "validation.csv", valid_rows, sorted({k for r in valid_rows for k in r}, key=lambda c: (c != "scene_id", c != "ok", c)))
    dropped = n - len(scenes)
    if dropped:
        log.warning("generate: %d group(s) failed pair validation and are excluded (see validation.csv)", dropped)
    if not scenes:
        raise PairedGTAError(
            f"generate: every scene failed pair validation ({out / 'validation.csv'}); "
            "inspect it or set generate.drop_invalid=false"
        )
    index = {
        "conditions": grid.names, "reference": grid.reference, "renderer": run.renderer.get("backend"),
        "width": run.renderer.get("width"), "height": run.renderer.get("height"),
        "scenes": scenes, "dropped_invalid": dropped, **renderer_versions(run.renderer.get("backend")),
    }
    write_json(out / INDEX, index)
    return {"num_scenes": len(scenes), "dropped_invalid": dropped}


def _write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)


@dataclass
class Generate:
    """The generate stage (pairedgta.stages.common.Stage): the run's dataset, rendered under every condition."""

    ctx: Context
    name: str = "generate"
    version: str = VERSION
    label: str = ""
    resumable: bool = True  # scenes land one by one in the work folder: a crash resumes where it stopped
    result_cls: type[GeneratedData] = GeneratedData

    def hash_config(self) -> dict[str, Any]:
        return hash_config(self.ctx.run, self.ctx.grid)

    def inputs(self) -> dict[str, str]:
        return {}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        return generate_dataset(self.ctx.run, self.ctx.grid, out)

    def shards(self) -> tuple[int, int]:
        return self.ctx.run.generate.num_shards, self.ctx.run.generate.shard

    def build_shard(self, key: str) -> Path | None:
        """Shards render straight into the entry's resumable work folder (no stage lock: they write disjoint
        per-scene folders, each renamed into place when complete), where the unsharded build resumes."""
        num, shard = self.shards()
        n = self.ctx.run.generate.num_scenes
        work = self.ctx.cache.partial_path(self.name, key)
        mine = list(range(shard, n, num))
        work.mkdir(parents=True, exist_ok=True)
        (work / SHARED_WORK).touch()
        log.info("generate shard %d of %d: %d of %d scenes -> %s", shard, num, len(mine), n, work)
        render_scenes(self.ctx.run, self.ctx.grid, work, mine)
        have = len(finished_scenes(work / "scenes"))
        if have == n:
            return None
        log.info("generate: %d of %d scenes rendered so far; the dataset is complete when every shard has run "
                 "(then run without generate.shard to go on)", have, n)
        return work


def will_compute(ctx: Context) -> bool:
    """Whether `run` would render (no intact cached dataset for this config, or generate is forced)."""
    return "generate" in ctx.force or ctx.cache.problem("generate", stage_key(Generate(ctx))) is not None


def run(ctx: Context) -> GeneratedData:
    """The dataset of `ctx`'s config, cached (the step below, and scripts that only need the data)."""
    result = run_cached(ctx, Generate(ctx))
    assert isinstance(result, GeneratedData)
    return result


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass (scope "dataset"): render the pass's dataset when `dataset.root` is null and
    open it; a pass whose root names a dataset (opened by planning.open_pass) skips it."""
    from pairedgta.datasets import open_dataset

    dcfg, plan = dict(ctx.cfg["dataset"]), state.plan
    if dcfg.get("root") is not None:
        if ctx.grid.corrupted and p.dataset is not None:  # corrupt its clean images (a cached entry of their own)
            from pairedgta.stages.corrupt_existing import corrupt_existing

            corrupt_existing(ctx, p, plan)
            return
        if Generate.name in plan.stages:
            log.info("generate: skipped, dataset.root=%s is an existing dataset", dcfg.get("root"))
        return
    if plan.steps("pass") and will_compute(ctx):
        from pairedgta.models.availability import check_available

        check_available([*state.models.evaluated, state.models.reference])  # before minutes of rendering
    gen = run(ctx)
    state.summary["generate"] = str(gen.path)
    if not gen.complete:  # a shard job: other shards still have scenes to render
        if plan.steps("pass", "run"):
            raise ConfigError(
                "generate.shard is set and other shards' scenes are still missing: run the remaining shards, "
                "then the later stages without generate.shard/num_shards"
            )
        return
    dataset = open_dataset(dcfg, ctx.grid, root=gen.path)
    p.dataset, p.dataset_key, p.generate = dataset, f"generate:{gen.key}", gen
    p.grid = dataset.grid or ctx.grid
