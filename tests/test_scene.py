"""Scene model: descriptor round trip, location sampling and object placement invariants."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pairedgta.errors import ConfigError, DataError
from pairedgta.scene import CameraPose, DynamicObject, Location, SceneDescriptor
from pairedgta.scene.placement import SURFACE, PlacementConfig, clear_of_ego, place_objects
from pairedgta.scene.sampling import PolygonRegion, RectangleRegion, build_region, world_offset


def test_descriptor_json_round_trip(tmp_path):
    d = SceneDescriptor(
        scene_id="00007", seed=42, location=Location(1.5, -2.0, 30.0, 90.0), camera=CameraPose(fov=70.0),
        objects=(DynamicObject("car", "sultan", 12.0, 1.5, heading=180.0, color=(1, 2, 3)),),
        region="los_santos", requested_objects=2,
    )
    d.save(tmp_path / "d.json")
    assert SceneDescriptor.load(tmp_path / "d.json") == d
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(DataError, match="bad.json: not valid JSON"):
        SceneDescriptor.load(tmp_path / "bad.json")
    with pytest.raises(DataError, match="category 'tank'"):
        DynamicObject("tank", "x", 1.0, 1.0)


def test_heading_convention_is_gta():
    loc = Location(0.0, 0.0, heading=90.0)  # facing -x (west), right-hand side is +y (north)
    x, y = world_offset(loc, forward=10.0, right=0.0)
    assert (round(x, 6), round(y, 6)) == (-10.0, 0.0)
    x, y = world_offset(loc, forward=0.0, right=2.0)
    assert (round(x, 6), round(y, 6)) == (0.0, 2.0)


def test_polygon_sampling_is_inside_valid_outside_excluded_and_uniform():
    region = PolygonRegion(
        "test", valid=[[[0, 0], [10, 0], [10, 10], [0, 10]], [[20, 0], [30, 0], [30, 10], [20, 10]]],
        excluded=[[[0, 0], [5, 0], [5, 10], [0, 10]]],
    )
    rng = np.random.default_rng(0)
    pts = np.array([[loc.x, loc.y] for loc in (region.sample_location(rng) for _ in range(3000))])
    assert region.contains(pts).all()
    assert not ((pts[:, 0] < 5) & (pts[:, 0] >= 0)).any()
    # uniform by area: the right square has twice the valid area of the left half-square
    share_right = np.mean(pts[:, 0] >= 20)
    assert abs(share_right - 2 / 3) < 0.04
    # seeded
    a = region.sample_location(np.random.default_rng(5))
    assert a == region.sample_location(np.random.default_rng(5))


def test_region_config_errors():
    with pytest.raises(ConfigError, match="region.type='hexagon'"):
        build_region({"type": "hexagon"})
    with pytest.raises(ConfigError, match=">= 3"):
        PolygonRegion("r", valid=[[[0, 0], [1, 1]]])
    everything_excluded = PolygonRegion("r", valid=[[[0, 0], [1, 0], [1, 1]]], excluded=[[[-1, -1], [2, -1], [2, 2], [-1, 2]]], max_tries=1000)
    with pytest.raises(DataError, match="no valid location"):
        everything_excluded.sample_location(np.random.default_rng(0))
    with pytest.raises(ConfigError, match="min=4, max=2"):
        PlacementConfig.from_cfg({"min": 4, "max": 2})


class Striped:
    """Road for |right| < 4 m around the x axis, sidewalk beyond: a region with real surfaces."""

    name = "striped"

    def sample_location(self, rng):
        return Location(0.0, 0.0, heading=270.0)  # facing +x along the road

    def surface_at(self, x, y):
        return "road" if abs(y) < 4 else ("sidewalk" if abs(y) < 7 else "other")


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    lo=st.integers(0, 4), extra=st.integers(0, 6),
    d_min=st.floats(0.0, 12.0),
    fwd=st.tuples(st.floats(2.0, 20.0), st.floats(0.0, 40.0)),
    lat=st.floats(0.5, 10.0),
)
def test_placement_invariants(seed, lo, extra, d_min, fwd, lat):
    cfg = PlacementConfig.from_cfg({
        "min": lo, "max": lo + extra, "d_min": d_min, "forward_range": [fwd[0], fwd[0] + fwd[1]],
        "lateral_range": [-lat, lat], "max_tries": 50,
    })
    region = Striped()
    loc = region.sample_location(None)
    objects, requested = place_objects(np.random.default_rng(seed), loc, region, cfg)
    assert lo <= requested <= lo + extra and len(objects) <= requested
    for o in objects:
        assert fwd[0] <= o.forward <= fwd[0] + fwd[1] + 1e-9 and -lat - 1e-9 <= o.right <= lat + 1e-9
        assert region.surface_at(*world_offset(loc, o.forward, o.right)) == SURFACE[o.category]
        assert clear_of_ego(o.category, o.model, o.forward, o.right)
    for i, a in enumerate(objects):
        for b in objects[i + 1:]:
            assert math.hypot(a.forward - b.forward, a.right - b.right) >= d_min - 1e-9
    # the same seed gives the same objects
    assert place_objects(np.random.default_rng(seed), loc, region, cfg) == (objects, requested)


def test_no_object_encloses_the_camera():
    # a 12 m bus centred 6 m ahead reaches back past the camera: the frame would be one class
    assert not clear_of_ego("bus", "bus", 6.0, 0.0)
    assert clear_of_ego("bus", "bus", 6.0, 3.5) and clear_of_ego("bus", "bus", 9.5, 0.0)
    assert clear_of_ego("car", "blista", 6.0, 0.0) and clear_of_ego("person", "x", 6.0, 0.0)
    cfg = PlacementConfig.from_cfg({"min": 3, "max": 3, "categories": ["bus", "truck"], "d_min": 0.0,
                                    "forward_range": [6, 12], "lateral_range": [-2, 2]})
    region = RectangleRegion("r", [-1e3, 1e3], [-1e3, 1e3])
    for seed in range(30):
        objects, _ = place_objects(np.random.default_rng(seed), Location(0, 0), region, cfg)
        for o in objects:
            half = 6.05 if o.category == "bus" else 3.8
            assert o.forward - half >= 3.1 or abs(o.right) >= 2.3, o


def test_placement_places_fewer_when_the_region_is_too_small():
    cfg = PlacementConfig.from_cfg({"min": 3, "max": 3, "d_min": 50.0, "forward_range": [5, 10], "lateral_range": [-2, 2]})
    objects, requested = place_objects(np.random.default_rng(0), Location(0, 0), RectangleRegion("r", [-1e3, 1e3], [-1e3, 1e3]), cfg)
    assert requested == 3 and len(objects) == 1
