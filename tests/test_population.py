"""Ambient population of the procedural town (no bpy needed): densities, determinism, placement on
the right surfaces, no overlaps, descriptor round trip, models."""
from __future__ import annotations

import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from pairedgta.errors import ConfigError
from pairedgta.render.blender import model_parts
from pairedgta.render.blender.models import rider_vehicle
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.placement import PlacementConfig, place_objects
from pairedgta.scene.population import CAR_MODELS, footprint
from pairedgta.scene.town import ProceduralTownRegion
from pairedgta.testing.cli import CONF

REGION = OmegaConf.to_container(OmegaConf.load(CONF / "region" / "procedural_town.yaml"))
REGION.pop("type")


@pytest.fixture(scope="module")
def town() -> ProceduralTownRegion:
    return ProceduralTownRegion(**REGION)


def _scene(town, k: int) -> SceneDescriptor:
    rng = np.random.default_rng(100 + k)
    loc = town.sample_location(rng)
    objects, requested = place_objects(rng, loc, town, PlacementConfig())
    d = SceneDescriptor(scene_id=f"{k:05d}", seed=100 + k, location=loc, objects=objects, region=town.name,
                        requested_objects=requested, extra=(("town", town.params()),))
    return town.populate(d)


@pytest.fixture(scope="module")
def scenes(town) -> list[SceneDescriptor]:
    return [_scene(town, k) for k in range(12)]


def _corners(x, y, heading, length, width) -> np.ndarray:
    h = math.radians(heading)
    fwd, right = np.array([-math.sin(h), math.cos(h)]), np.array([math.cos(h), math.sin(h)])
    return np.array([[x, y] + fwd * a * length / 2 + right * b * width / 2 for a, b in ((1, 1), (1, -1), (-1, -1), (-1, 1))])


def _overlap(p: np.ndarray, q: np.ndarray) -> bool:
    """Separating-axis test of two convex quadrilaterals."""
    for poly in (p, q):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            a, b = p @ axis, q @ axis
            if a.max() <= b.min() or b.max() <= a.min():
                return False
    return True


def _near(quad: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Rows (centre x, y; size x, y in columns 3, 4) whose bounding circle meets the quad's: only
    these can overlap it, so the exact test runs on them alone (a town has thousands of rows)."""
    centre = quad.mean(axis=0)
    reach = np.linalg.norm(quad - centre, axis=1).max() + np.hypot(rows[:, 3], rows[:, 4]) / 2
    return np.hypot(rows[:, 0] - centre[0], rows[:, 1] - centre[1]) <= reach + 1e-6


def _footprints(d: SceneDescriptor) -> list[tuple[str, np.ndarray]]:
    loc = d.location
    h = math.radians(loc.heading)
    fwd, right = np.array([-math.sin(h), math.cos(h)]), np.array([math.cos(h), math.sin(h)])
    out = [("ego", _corners(loc.x, loc.y, loc.heading, 4.6, 1.8))]
    for o in d.objects:
        xy = np.array([loc.x, loc.y]) + fwd * o.forward + right * o.right
        out.append((f"object {o.category}", _corners(*xy, loc.heading + o.heading, *footprint(o.category, o.model))))
    for e in d.ambient:
        length, width = footprint(e.category, e.model)
        if e.category == "person":
            length, width = (0.45 + 0.7 * abs(e.pose)) * e.scale, 0.5 * e.scale
        out.append((f"{e.role} {e.category}", _corners(e.x, e.y, e.heading, length, width)))
    return out


def test_every_scene_is_populated_with_the_paper_subjects(scenes):
    for d in scenes:
        cats = {e.category for e in d.ambient}
        assert len(d.ambient) >= 15, d.scene_id
        assert "car" in cats and "person" in cats, (d.scene_id, cats)
    roles = {(e.category, e.role) for d in scenes for e in d.ambient}
    for want in (("car", "parked"), ("car", "lane"), ("person", "sidewalk"), ("person", "crossing"), ("rider", "lane")):
        assert want in roles, want
    assert {"bus", "truck"} & {c for c, _ in roles}
    assert {rider_vehicle(e.model) for d in scenes for e in d.ambient if e.category == "rider"} == {"bicycle",
                                                                                                     "motorcycle"}


def test_population_is_a_function_of_the_scene_seed(town, scenes):
    again = _scene(town, 3)
    assert again.ambient == scenes[3].ambient
    assert scenes[3].ambient != scenes[4].ambient
    # the dynamic objects (the paper's 0-3 with d_min) are untouched by the population
    rng = np.random.default_rng(103)
    loc = town.sample_location(rng)
    objects, _ = place_objects(rng, loc, town, PlacementConfig())
    assert scenes[3].objects == objects


def test_nothing_overlaps(town, scenes):
    layout = town.layout()
    furniture = np.concatenate([layout.groups[key] for key in (("cylinder", "metal", "pole"),
                                                                 ("cylinder", "bark", "vegetation"))])
    solids = layout.solids
    for d in scenes:
        shapes = _footprints(d)
        for i in range(len(shapes)):
            for j in range(i + 1, len(shapes)):
                if shapes[i][0].startswith("object") and shapes[j][0].startswith("object"):
                    continue  # dynamic objects keep d_min between centres, as in the paper
                if shapes[i][0] == "ego" and shapes[j][0].startswith("object"):
                    continue  # R_k starts 6 m ahead: the paper's own placement
                assert not _overlap(shapes[i][1], shapes[j][1]), (d.scene_id, shapes[i][0], shapes[j][0])
        for name, quad in shapes[1 + len(d.objects):]:
            for rows, what in ((furniture, "street furniture"), (solids, "building")):
                for r in rows[_near(quad, rows)]:
                    assert not _overlap(quad, _corners(r[0], r[1], 0.0, r[4], r[3])), (d.scene_id, name, what)


def test_entities_stand_where_they_belong(town, scenes):
    hw = town.road_width / 2
    for d in scenes:
        for e in d.ambient:
            surface = town.surface_at(e.x, e.y)
            if e.role in ("lane", "parked") and e.category in ("car", "truck", "bus", "rider"):
                assert surface == "road", e
                assert e.heading % 90 < 5 or e.heading % 90 > 85, e  # along the street
            elif e.role == "sidewalk" or (e.role == "parked" and e.category in ("bicycle", "motorcycle")):
                assert surface == "sidewalk", e
            elif e.role == "crossing":
                assert surface == "road", e
            if e.role == "lane":
                # keep right: the lane's offset from the road centre is on the right of travel
                h = math.radians(e.heading)
                right = np.array([math.cos(h), math.sin(h)])
                c = town.road_centres
                across = e.x if abs(right[0]) > 0.5 else e.y
                centre = c[np.argmin(np.abs(c - across))]
                assert 0 < (across - centre) * (right[0] if abs(right[0]) > 0.5 else right[1]) < hw, e
    people = [e for d in scenes for e in d.ambient if e.category == "person"]
    heights = [e.scale for e in people]
    assert min(heights) < 0.95 and max(heights) > 1.05  # varied heights
    assert len({e.color for e in people}) >= 6  # varied clothing
    assert any(e.pose != 0 for e in people) and any(e.pose == 0 for e in people)


def test_zero_densities_give_an_empty_ambient_set(town, scenes):
    zero = {k: 0.0 for k in REGION["population"] if k.endswith("_100m") or k == "crossing_pedestrians"}
    empty = ProceduralTownRegion(**{**REGION, "population": {**REGION["population"], **zero}})
    d = scenes[0]
    assert empty.populate(d).ambient == ()
    assert ProceduralTownRegion(**{**REGION, "population": None}).populate(d).ambient == ()
    # one density on, the rest off: only that kind appears
    only = ProceduralTownRegion(**{**REGION, "population": {**REGION["population"], **zero,
                                                             "pedestrians_per_100m": 10.0}})
    assert {(e.category, e.role) for e in only.populate(d).ambient} == {("person", "sidewalk")}


def test_descriptor_round_trip_keeps_the_population(scenes, tmp_path):
    d = scenes[1]
    d.save(tmp_path / "d.json")
    back = SceneDescriptor.load(tmp_path / "d.json")
    assert back == d and len(back.ambient) == len(d.ambient)
    # a descriptor from before the population (schema 1) loads with an empty ambient set
    data = d.to_dict()
    data.pop("ambient")
    assert SceneDescriptor.from_dict(data).ambient == ()


@pytest.mark.parametrize("bad, key", [({"pedestrians_per_100m": -1}, "pedestrians_per_100m"),
                                      ({"heavy_share": 2.0}, "heavy_share"),
                                      ({"peds": 3}, "peds"),
                                      ({"radius": "far"}, "population")])
def test_bad_population_values_are_config_errors(bad, key):
    with pytest.raises(ConfigError, match=key) as err:
        ProceduralTownRegion(**{**REGION, "population": {**REGION["population"], **bad}})
    assert "\n" not in str(err.value)


def test_rider_models_ride_the_right_vehicle():
    for model, vehicle in (("a_m_y_motox_01", "motorcycle"), ("a_m_y_motox_02", "motorcycle"),
                           ("a_m_y_cyclist_01", "bicycle"), ("a_m_y_roadcyc_01", "bicycle")):
        parts, _ = model_parts("rider", model, (200, 0, 0), (0, 0, 0))
        assert {p[0] for p in parts} == {"rider", vehicle}, model


def test_people_have_limbs_poses_and_heights():
    stand, _ = model_parts("person", "a_m_y_business_01", (10, 20, 30), (40, 50, 60))
    walk, _ = model_parts("person", "a_m_y_business_01", (10, 20, 30), (40, 50, 60), pose=1.0)
    tall, _ = model_parts("person", "a_m_y_business_01", (10, 20, 30), (40, 50, 60), scale=1.1)
    assert len(stand) >= 14  # legs, shoes, hips, torso, neck, head, hair, two-part arms, hands
    rows = np.array([p[3] for p in stand])
    assert rows.shape[1] == 12 and (rows[:, 11] != 0).sum() >= 8  # hanging limbs have a pitch
    swung = np.array([p[3] for p in walk])[:, 11]
    assert not np.array_equal(swung, rows[:, 11])  # walking swings the limbs
    top = lambda ps: max(p[3][2] + (p[3][5] if p[3][11] == 0 else 0) for p in ps)  # noqa: E731
    assert 1.6 < top(stand) < 1.9 and top(tall) == pytest.approx(1.1 * top(stand), rel=0.02)


def test_cars_come_in_sizes_and_light_up_only_when_driving():
    sizes = {}
    for model in ("blista", "premier", "baller", "speedo"):
        parts, spots = model_parts("car", model, (200, 0, 0), (0, 0, 0))
        rows = np.array([p[3] for p in parts])
        sizes[model] = float((rows[:, 2] + rows[:, 5]).max())
        assert {"paint", "glass", "rubber", "headlight", "taillight"} <= {p[2] for p in parts}
        assert spots
        parked, none = model_parts("car", model, (200, 0, 0), (0, 0, 0), lit=False)
        assert none == [] and not {"headlight", "taillight"} & {p[2] for p in parked}
    assert sizes["blista"] < sizes["baller"] < sizes["speedo"]
    assert sizes["speedo"] == pytest.approx(CAR_MODELS["speedo"][2], abs=0.05)


def test_the_generate_stage_populates_every_scene():
    """The main job's scenes carry the population (not only the benches'), and it replays from the descriptor."""
    from omegaconf import OmegaConf as OC

    from pairedgta.scene.sampling import build_region
    from pairedgta.stages.generate import build_descriptor
    from pairedgta.testing.cli import compose_cfg

    from pairedgta import schema

    cfg = OC.to_container(compose_cfg(["region=procedural_town"]), resolve=True)
    gen = schema.parse(cfg).generate
    region = build_region(cfg["region"])
    descriptors = [build_descriptor(k, gen, region)[0] for k in range(4)]
    kinds = {e.category for d in descriptors for e in d.ambient}
    assert {"car", "person"} <= kinds, kinds
    assert all(len(d.ambient) >= 10 for d in descriptors)
    again = build_descriptor(2, gen, build_region(cfg["region"]))[0]
    assert again.ambient == descriptors[2].ambient
    cfg["region"]["population"] = None
    assert build_descriptor(0, gen, build_region(cfg["region"]))[0].ambient == ()
