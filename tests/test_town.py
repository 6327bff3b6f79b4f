"""Procedural town: determinism, lane sampling, surfaces and layout content (no bpy needed)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pairedgta.errors import ConfigError
from pairedgta.scene.town import ProceduralTownRegion
from pairedgta.scene.town_primitives import SHAPES, town_palette


@pytest.fixture(scope="module")
def town() -> ProceduralTownRegion:
    return ProceduralTownRegion(town_seed=7, blocks=3)


def test_layout_is_a_function_of_the_parameters(town):
    again = ProceduralTownRegion(town_seed=7, blocks=3).layout()
    layout = town.layout()
    assert list(layout.groups) == list(again.groups)
    for key in layout.groups:
        np.testing.assert_array_equal(layout.groups[key], again.groups[key])
    np.testing.assert_array_equal(layout.lamps, again.lamps)
    np.testing.assert_array_equal(layout.solids, again.solids)
    other = ProceduralTownRegion(town_seed=8, blocks=3).layout()
    assert not np.array_equal(
        layout.groups[("box", "facade", "building")], other.groups[("box", "facade", "building")]
    )


def test_layout_covers_the_static_classes(town):
    layout = town.layout()
    labels = {label for _, _, label in layout.groups}
    for cls in ("road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
                "vegetation", "terrain"):
        assert cls in labels, cls
    assert {shape for shape, _, _ in layout.groups} <= set(SHAPES)
    assert len(layout.lamps) > 0 and len(layout.solids) > 0
    assert all(a.shape[1] == 11 and np.isfinite(a).all() for a in layout.groups.values())


def test_sample_location_lands_on_the_right_lane_between_junctions(town):
    rng = np.random.default_rng(0)
    hw = town.road_width / 2
    centres = town.road_centres
    for _ in range(300):
        loc = town.sample_location(rng)
        assert town.surface_at(loc.x, loc.y) == "road"
        assert loc.heading in (0.0, 90.0, 180.0, 270.0)
        h = math.radians(loc.heading)
        fx, fy = -math.sin(h), math.cos(h)
        rx, ry = math.cos(h), math.sin(h)
        # the nearest road centre line runs along the heading; the ego keeps right of it
        along_y = abs(fx) < 0.5
        centre = centres[np.argmin(np.abs(centres - (loc.x if along_y else loc.y)))]
        offset = ((loc.x - centre) * rx) if along_y else ((loc.y - centre) * ry)
        assert 0.0 < offset < hw
        # not inside a junction, and at least 15 m of street before the next one
        pos = loc.y if along_y else loc.x
        direction = fy if along_y else fx
        ahead = [(c - pos) * direction for c in centres if (c - pos) * direction > 0]
        assert min(abs(pos - c) for c in centres) > hw + town.sidewalk_width
        if ahead:
            assert min(ahead) - hw - town.sidewalk_width >= 15.0 - 1e-6
        assert not town.obstacle_at(loc.x, loc.y, 1.6)
    # same generator state -> same locations
    a = [town.sample_location(np.random.default_rng(3)) for _ in range(2)]
    assert a[0] == a[1]


def test_surface_at(town):
    c = town.road_centres
    hw, sw = town.road_width / 2, town.sidewalk_width
    assert town.surface_at(c[1], 10.0) == "road"
    assert town.surface_at(c[1] + hw + sw / 2, c[0] + 20) == "sidewalk"
    assert town.surface_at(c[1] - hw - sw / 2, c[1] + 20) == "sidewalk"
    mid = (c[0] + c[1]) / 2
    assert town.surface_at(mid, mid) == "other"  # inside a block
    assert town.surface_at(5000.0, 5000.0) == "other"
    assert town.ground_height(c[1], 10.0) == 0.0
    assert town.ground_height(c[1] + hw + sw / 2, c[0] + 20) == pytest.approx(town.kerb_height)


def test_buildings_stand_on_lots_only(town):
    solids = town.layout().solids
    hw = town.road_width / 2
    railings = 0
    for cx, cy, cz, sx, sy, sz, _ in solids:
        assert town.obstacle_at(float(cx), float(cy), float(cz + sz / 2))
        if town.surface_at(float(cx), float(cy)) == "other":
            continue
        # the only solids off the lots: 1 m guard railings along the kerb, never on the road
        railings += 1
        across = cx if min(sx, sy) == sx else cy
        assert abs(min(abs(across - town.road_centres)) - (hw + 0.3)) < 1e-3
        assert sz == pytest.approx(1.0) and min(sx, sy) < 0.31
    assert railings > 0


def test_thin_classes_are_built_along_the_streets(town):
    """Signs, fences and walls are common enough to be learnt: every kerb gets signs facing its
    traffic, and the three thin classes all exist in one town."""
    from pairedgta.scene.town import ProceduralTownRegion

    labels = {label for (_, _, label) in town.layout().groups}
    assert {"traffic sign", "fence", "wall"} <= labels
    signs = sum(len(v) for (_, m, label), v in town.layout().groups.items() if label == "traffic sign" and m == "sign")
    bare = ProceduralTownRegion(town_seed=town.town_seed, blocks=town.blocks, signs_per_100m=0.0,
                                junction_sign_fraction=0.0, railing_fraction=0.0)
    assert not any(label == "traffic sign" for (_, _, label) in bare.layout().groups)
    street_km = 2 * 2 * len(town.road_centres) * (town.road_centres[-1] - town.road_centres[0]) / 1000
    assert signs >= 0.5 * town.signs_per_100m * 10 * street_km  # kerbs x km x signs/km, minus junctions
    # plates face the traffic of their side: on an east kerb of a north-south street, south
    rows = town.layout().groups[("disc", "sign", "traffic sign")]
    hw = town.road_width / 2
    c = town.road_centres
    east = [r for r in rows if np.isclose(min(abs(r[0] - c - hw - 0.45)), 0, atol=0.1)]
    assert east and all(np.isclose(r[6] % 360, 180.0) for r in east)


def test_bad_parameters_are_one_line_config_errors():
    from pairedgta.scene.sampling import build_region

    with pytest.raises(ConfigError, match=r"region: unknown key\(s\) lanes; known keys: .*road_width"):
        build_region({"type": "procedural_town", "town_seed": 0, "lanes": 3})
    with pytest.raises(ConfigError, match="road_width"):
        ProceduralTownRegion(road_width=2.0)
    with pytest.raises(ConfigError, match="blocks"):
        ProceduralTownRegion(blocks=0)
    with pytest.raises(ConfigError, match=r"material_variation=1.5 is invalid; set it in \[0, 1\]"):
        ProceduralTownRegion(material_variation=1.5)


def _colours(town: ProceduralTownRegion, material: str) -> np.ndarray:
    rows = [a for (_, mat, _), a in town.layout().groups.items() if mat == material]
    return np.concatenate(rows)[:, 7:10]


def test_towns_differ_in_ground_materials_and_share_one_palette_at_zero_variation():
    # one asphalt grey for every town lets a model learn "road = that grey"; towns must differ
    asphalt = [town_palette(seed, 1.0)["asphalt"] for seed in range(40)]
    grey = np.array([np.mean(a) for a in asphalt])
    assert grey.max() - grey.min() > 0.15 and len(set(grey.tolist())) == 40
    assert len({town_palette(s, 1.0)["paving"] for s in range(40)}) == 40
    assert town_palette(3, 1.0) == town_palette(3, 1.0)
    assert town_palette(3, 0.0) == town_palette(4, 0.0)  # 0: the reference palette, no road repairs
    assert town_palette(3, 0.0)["wear"] == 0.0

    # the layout uses them: road planes in the town's asphalt, repair patches darker or lighter
    for seed in (1, 2):
        t = ProceduralTownRegion(town_seed=seed, blocks=2)
        road = _colours(t, "asphalt")
        base = np.array(town_palette(seed, 1.0)["asphalt"])
        assert np.isclose(road, base, atol=1e-6).all(axis=1).sum() >= 3  # the road surfaces
        assert (~np.isclose(road, base, atol=1e-6).all(axis=1)).sum() > 0  # the patches
        assert np.allclose(_colours(t, "sidewalk"), town_palette(seed, 1.0)["paving"], atol=1e-6)
    flat = ProceduralTownRegion(town_seed=1, blocks=2, material_variation=0.0)
    assert np.allclose(_colours(flat, "asphalt"), town_palette(0, 0.0)["asphalt"], atol=1e-6)
    # the palette draws from its own stream: buildings are where they were
    np.testing.assert_array_equal(flat.layout().solids, ProceduralTownRegion(town_seed=1, blocks=2).layout().solids)


def test_region_dispatch_builds_the_town_from_its_config():
    from pairedgta.scene import sampling
    from omegaconf import OmegaConf

    from pairedgta.testing.cli import CONF

    cfg = OmegaConf.to_container(OmegaConf.load(CONF / "region" / "procedural_town.yaml"))
    region = sampling.build_region(cfg)
    assert isinstance(region, ProceduralTownRegion) and region.name == "procedural_town"
    loc = region.sample_location(np.random.default_rng(0))
    assert region.surface_at(loc.x, loc.y) == "road"


@pytest.mark.parametrize("key, value", [("signs_per_100m", -1.0), ("junction_sign_fraction", 1.5),
                                        ("railing_fraction", -0.1), ("front_boundary_fraction", 2.0)])
def test_street_furniture_densities_are_checked(key, value):
    with pytest.raises(ConfigError, match=rf"region procedural_town: {key}=.* is invalid; set it") as err:
        ProceduralTownRegion(**{key: value})
    assert "\n" not in str(err.value)
