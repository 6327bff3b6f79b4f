"""pairedgta/conf/region/los_santos.yaml holds every location the paper sampled."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import yaml
from matplotlib.path import Path as PolygonPath

from pairedgta.configs import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[1]
REGION = CONFIG_DIR / "region" / "los_santos.yaml"
PAPER_TIMES = ROOT / "pairedgta" / "data" / "paper_generation_times.csv"  # the paper's sampled locations


@pytest.fixture(scope="module")
def region() -> dict:
    return yaml.safe_load(REGION.read_text())


@pytest.fixture(scope="module")
def paper_locations() -> list[tuple[float, float]]:
    with PAPER_TIMES.open(newline="") as fh:
        return [(float(r["x"]), float(r["y"])) for r in csv.DictReader(fh)]


def polygons(region: dict, key: str) -> list[PolygonPath]:
    return [PolygonPath([(float(x), float(y)) for x, y in poly]) for poly in region[key]]


def test_region_schema(region):
    assert region["type"] == "polygons" and region["name"] == "los_santos"
    for key in ("valid", "excluded"):
        assert isinstance(region[key], list) and region[key], key
        for poly in region[key]:
            assert len(poly) >= 3
            for vertex in poly:
                assert len(vertex) == 2 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in vertex)
                assert -4000 <= vertex[0] <= 4500 and -4000 <= vertex[1] <= 8000  # inside the GTA V map


def test_every_paper_location_is_valid_and_not_excluded(region, paper_locations):
    valid, excluded = polygons(region, "valid"), polygons(region, "excluded")
    assert len(paper_locations) == 100
    outside = [p for p in paper_locations if not any(poly.contains_point(p) for poly in valid)]
    in_hole = [p for p in paper_locations if any(poly.contains_point(p) for poly in excluded)]
    assert outside == [] and in_hole == []


def test_excluded_areas_cut_into_the_valid_area(region):
    valid = polygons(region, "valid")
    for poly in region["excluded"]:
        assert any(v.contains_point(tuple(vertex)) for v in valid for vertex in poly), poly


def test_known_places(region):
    valid, excluded = polygons(region, "valid"), polygons(region, "excluded")

    def ok(p):
        return any(v.contains_point(p) for v in valid) and not any(e.contains_point(p) for e in excluded)

    assert ok((195.0, -933.0))  # Legion Square, downtown
    assert ok((-1200.0, -1570.0))  # Vespucci Beach boardwalk
    assert not ok((-1600.0, -1600.0))  # ocean off Vespucci Beach
    assert not ok((-1000.0, -3000.0))  # LSIA runways: not part of the street region
    assert not ok((2500.0, 4000.0))  # Blaine County
