"""The shipped demo model: loads offline from the package, segments freshly rendered held-out
daytime scenes above the floor in its model card, and degrades gradually: less at a clear sunset than
at a clear night, and most at a foggy night."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from pairedgta.conditions import build_condition_grid
from pairedgta.metrics import ConfusionMatrix, ReferenceConsistency
from pairedgta.models import build_segmenter
from pairedgta.render import build_renderer
from pairedgta.scene.placement import PlacementConfig, place_objects
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.sampling import build_region
from pairedgta.testing.cli import compose_cfg

WEIGHTS = Path(__file__).resolve().parents[1] / "pairedgta" / "models" / "weights" / "demo_segformer"


def test_shipped_weights_load_offline_and_are_small():
    files = {p.name for p in WEIGHTS.iterdir()}
    assert {"model.safetensors", "config.json", "model_card.json", "README.md"} <= files
    assert (WEIGHTS / "model.safetensors").stat().st_size <= 16 * 2**20
    seg = build_segmenter("demo_segformer")
    assert sum(p.numel() for p in seg.module.parameters()) <= 4_000_000
    probs = seg.predict_proba(torch.rand(1, 3, 64, 128))
    assert probs.shape == (1, 19, 64, 128)


def test_demo_model_on_fresh_held_out_scenes():
    card = json.loads((WEIGHTS / "model_card.json").read_text())
    cfg = OmegaConf.to_container(compose_cfg(["renderer=blender", "region=procedural_town"]), resolve=True)
    grid = build_condition_grid({**cfg["conditions"], "only": ["Day-EXTRASUNNY", "Sunset-EXTRASUNNY", "Night-EXTRASUNNY",
                                                              "Night-FOGGY"]})
    region = build_region(cfg["region"])
    seg = build_segmenter("demo_segformer")
    gt_cm = ConfusionMatrix()
    xi = {c: ReferenceConsistency() for c in ("Sunset-EXTRASUNNY", "Night-EXTRASUNNY", "Night-FOGGY")}
    with build_renderer(cfg["renderer"]) as renderer:
        for k in range(3):  # two scenes leave most of the 19 classes to a few hundred pixels
            seed = 300_000 + k  # disjoint from training (100000+), validation (200000+) and evaluation seeds
            rng = np.random.default_rng(seed)
            loc = region.sample_location(rng)
            objects, _ = place_objects(rng, loc, region, PlacementConfig.from_cfg(card["data"].get("objects", {"min": 1, "max": 3})))
            d = region.populate(SceneDescriptor(scene_id=f"t{k}", seed=seed, location=loc, objects=objects,
                                                region=region.name))  # traffic and pedestrians, as generate does
            renderer.prepare(d)
            out = {c.name: renderer.render(d, c) for c in grid}
            labels, _ = seg.predict(np.stack([out[c].image for c in grid.names]))
            pred = dict(zip(grid.names, labels.numpy()))
            gt_cm.update(out["Day-EXTRASUNNY"].labels, pred["Day-EXTRASUNNY"])
            ref = np.asarray(pred["Day-EXTRASUNNY"])
            for c, m in xi.items():
                m.update(ref, pred[c])
    assert gt_cm.miou() >= card["test_floor_miou"], (gt_cm.miou(), card["test_floor_miou"])
    assert xi["Sunset-EXTRASUNNY"].mean() > xi["Night-EXTRASUNNY"].mean() > xi["Night-FOGGY"].mean()
