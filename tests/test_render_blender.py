"""Blender backend: pairing proofs at tiny resolution, determinism, label content, bad input.

bpy is a dependency of the project (the default backend), so these tests always run.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from omegaconf import OmegaConf

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.conditions import Condition, build_condition_grid
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render import RENDERERS, build_renderer
from pairedgta.render.blender import (
    TEMPLATES,
    BlenderRenderer,
    decode_labels,
    label_code,
    lighting,
    mesh_arrays,
    model_parts,
)
from pairedgta.scene.descriptor import CATEGORIES, CameraPose, DynamicObject, Location, SceneDescriptor
from pairedgta.scene.town import ProceduralTownRegion
from pairedgta.testing.cli import CONF, compose_cfg

TOWN = {"town_seed": 1, "blocks": 2, "countryside_trees": 10}
ROAD, BUILDING, SKY, PERSON, CAR = (CLASS_NAMES.index(c) for c in ("road", "building", "sky", "person", "car"))
GRID = build_condition_grid(OmegaConf.to_container(OmegaConf.load(CONF / "conditions" / "paper.yaml")))


def _descriptor(**changes) -> SceneDescriptor:
    region = ProceduralTownRegion(**TOWN)
    loc = region.sample_location(np.random.default_rng(2))
    lane_to_sidewalk = region.road_width / 4 + region.sidewalk_width / 2
    objects = (
        DynamicObject("car", "sedan", forward=12.0, right=0.0, color=(200, 30, 30), secondary_color=(40, 40, 40)),
        DynamicObject("person", "walker", forward=9.0, right=lane_to_sidewalk, heading=90.0, color=(40, 90, 200)),
    )
    base = {"scene_id": "t0", "seed": 0, "location": loc, "objects": objects, "region": "procedural_town",
            "extra": (("town", TOWN),)}
    base.update(changes)
    return SceneDescriptor(**base)


# ---- no bpy needed -------------------------------------------------------------------------

def test_backend_is_registered_and_module_imports_without_bpy():
    assert RENDERERS.resolve("blender").__name__ == "BlenderRenderer"
    code = "import sys; import pairedgta.render.blender; assert 'bpy' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_mesh_templates_and_arrays():
    for shape, (verts, faces) in TEMPLATES.items():
        assert all(0 <= i < len(verts) for f in faces for i in f), shape
    rows = np.array([[1.0, 2.0, 0.0, 2.0, 4.0, 3.0, 90.0, 1.0, 0.5, 0.0, 0.25]])
    verts, _, starts, mats, cols = mesh_arrays([("box", rows, 3)])
    assert verts.shape == (8, 3) and len(starts) == 6 and set(mats) == {3}
    # yaw 90: the 4 m side now runs along x; base at z=0, top at z=3
    assert np.ptp(verts[:, 0]) == pytest.approx(4.0) and np.ptp(verts[:, 1]) == pytest.approx(2.0)
    assert verts[:, 2].min() == pytest.approx(0.0) and verts[:, 2].max() == pytest.approx(3.0)
    assert cols[0, 0] == pytest.approx(1.0) and cols[0, 3] == pytest.approx(0.25)


def test_label_codes_round_trip():
    codes = np.array([[0, label_code("road"), label_code("car", 5), label_code("void"), label_code("rider", 1023)]])
    train, inst = decode_labels(codes.astype(np.float32))
    assert train.tolist() == [[SKY, ROAD, CAR, 255, CLASS_NAMES.index("rider")]]
    assert inst.tolist() == [[0, 0, 5, 0, 1023]]


@pytest.mark.parametrize("category", CATEGORIES)
def test_every_category_has_a_real_size_model(category):
    parts, _ = model_parts(category, "m", (10, 20, 30), (40, 50, 60))
    rows = np.array([p[3] for p in parts])
    top = float((rows[:, 2] + rows[:, 5]).max())
    length = float((np.abs(rows[:, 1]) + rows[:, 4] / 2).max() * 2)
    expected_top = {"car": 1.4, "truck": 3.6, "bus": 3.2, "motorcycle": 1.0, "bicycle": 1.0, "person": 1.75,
                    "rider": 1.6}
    assert top == pytest.approx(expected_top[category], abs=0.25)
    assert length < 13.0
    if category == "rider":
        assert {p[0] for p in parts} == {"rider", "bicycle"}


def test_unknown_category_is_a_renderer_error():
    with pytest.raises(RendererError, match="category 'tank'"):
        model_parts("tank", "t", (0, 0, 0), (0, 0, 0))


def test_light_model_is_continuous_and_ordered():
    day, sunset, night = (lighting(GRID[n]) for n in ("Day-EXTRASUNNY", "Sunset-EXTRASUNNY", "Night-EXTRASUNNY"))
    assert day["sun_strength"] > sunset["sun_strength"] > night["sun_strength"] == 0.0
    assert sunset["sun_color"][2] < 0.5 < sunset["sun_color"][0]  # warm low sun
    assert day["light_level"] > sunset["light_level"] > night["light_level"] > 0  # what the camera meters
    assert night["lamps"] == 1.0 and day["lamps"] == 0.0
    # a small change of any physical field makes a small change of every parameter
    base = Condition(name="x", time="Day", weather="w", sun_elevation_deg=20.0, cloud_cover=0.3, visibility_m=400.0,
                     rain_mm_h=5.0, wetness=0.3)
    p0 = lighting(base)
    for field in ("sun_elevation_deg", "cloud_cover", "visibility_m", "rain_mm_h", "wetness"):
        p1 = lighting(dataclasses.replace(base, **{field: getattr(base, field) + 1e-3}))
        for key, value in p0.items():
            assert np.allclose(value, p1[key], atol=1e-2), (field, key)


def test_bad_options_are_config_errors():
    from pairedgta.render import build_renderer

    with pytest.raises(ConfigError, match=r"renderer: unknown key\(s\) sampels; known keys: .*samples"):
        build_renderer({"backend": "blender", "width": 64, "height": 32, "sampels": 4})
    with pytest.raises(ConfigError, match="renderer.device"):
        BlenderRenderer(width=64, height=32, device="TPU")
    with pytest.raises(ConfigError, match="renderer.fog_model is invalid; set it analytic or volume"):
        BlenderRenderer(width=64, height=32, fog_model="haze")


def test_analytic_fog_colour_follows_the_light():
    fog = {n: lighting(GRID[n]) for n in ("Day-FOGGY", "Sunset-FOGGY", "Night-FOGGY", "Day-EXTRASUNNY")}
    for name, p in fog.items():
        assert np.all(np.isfinite(p["fog_color"])) and np.all(p["fog_color"] >= 0), name
    lum = {n: float(np.mean(p["fog_color"])) for n, p in fog.items()}
    assert lum["Day-FOGGY"] > lum["Sunset-FOGGY"] > lum["Night-FOGGY"] > 0
    # at night the air is lit where the lamps are (the compositor's halos), not uniformly: the fog colour
    # is the sky's and the city glow's, darker than a twentieth of the day's
    assert lum["Night-FOGGY"] < 0.05 * lum["Day-FOGGY"]
    day, sunset = fog["Day-FOGGY"]["fog_color"], fog["Sunset-FOGGY"]["fog_color"]
    assert sunset[0] / sunset[2] > day[0] / day[2]  # warmer at sunset
    assert fog["Day-EXTRASUNNY"]["extinction"] == 0.0 < fog["Day-FOGGY"]["extinction"]


def test_missing_bpy_is_a_one_line_renderer_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "bpy", None)
    r = BlenderRenderer(width=64, height=32)
    with pytest.raises(RendererError, match="renderer=blender needs Blender as a Python module") as err:
        r.open()
    assert "\n" not in str(err.value)


def test_config_files_build_the_renderer_and_region():
    cfg = compose_cfg(["renderer=blender", "region=procedural_town"])
    rcfg = OmegaConf.to_container(cfg.renderer, resolve=True)
    renderer = build_renderer(rcfg)
    assert isinstance(renderer, BlenderRenderer) and renderer.gives_labels
    assert (renderer.width, renderer.height) == (512, 256)
    assert renderer.town_cfg["town_seed"] == cfg.region.town_seed
    with pytest.raises(ConfigError, match="region=procedural_town"):
        build_renderer(OmegaConf.to_container(compose_cfg(["renderer=blender", "region=los_santos"]).renderer, resolve=True))


# ---- rendering -----------------------------------------------------------------------------


CONDITIONS = ("Day-EXTRASUNNY", "Sunset-FOGGY", "Night-RAIN", "Day-FOGGY")


@pytest.fixture(scope="module")
def rendered():
    """Four conditions of one scene, labels re-rendered for every condition, then the first
    condition again."""
    d = _descriptor()
    r = BlenderRenderer(width=96, height=48, samples=2, town=TOWN, labels_per_condition=True)
    r.open()
    try:
        results = {name: r.render(d, GRID[name]) for name in CONDITIONS}
        again = r.render(d, GRID[CONDITIONS[0]])
    finally:
        r.close()
    return d, results, again


@pytest.mark.slow
def test_labels_and_instances_are_identical_across_conditions_while_images_differ(rendered):
    _, results, _ = rendered
    ref = results[CONDITIONS[0]]
    assert ref.image.shape == (48, 96, 3) and ref.image.dtype == np.uint8
    assert ref.labels.shape == (48, 96) and ref.labels.dtype == np.uint8
    assert ref.instances.shape == (48, 96) and ref.instances.dtype == np.uint16
    for name in CONDITIONS[1:]:
        res = results[name]
        np.testing.assert_array_equal(res.labels, ref.labels, err_msg=name)
        np.testing.assert_array_equal(res.instances, ref.instances, err_msg=name)
    images = [results[n].image.astype(np.int16) for n in CONDITIONS]
    for i in range(len(images)):
        for j in range(i + 1, len(images)):
            assert np.abs(images[i] - images[j]).mean() > 5.0, (CONDITIONS[i], CONDITIONS[j])
    for name, res in results.items():  # exposure keeps every condition visible
        assert res.image.mean() > 15 and res.image.std() > 8, name


@pytest.mark.slow
def test_same_descriptor_and_condition_give_the_same_image(rendered):
    _, results, again = rendered
    first = results[CONDITIONS[0]]
    np.testing.assert_array_equal(again.image, first.image)
    np.testing.assert_array_equal(again.labels, first.labels)


@pytest.mark.slow
def test_images_do_not_depend_on_what_was_rendered_before(rendered):
    """A second renderer in the same process that caches labels, first renders another scene at
    night, then this scene's conditions in reverse order, reproduces every image bit for bit."""
    d, results, _ = rendered
    loc = ProceduralTownRegion(**TOWN).sample_location(np.random.default_rng(5))
    other = _descriptor(scene_id="t1", location=loc)
    assert other.location != d.location
    with BlenderRenderer(width=96, height=48, samples=2, town=TOWN) as r:
        r.render(other, GRID["Night-EXTRASUNNY"])
        again = {name: r.render(d, GRID[name]) for name in reversed(CONDITIONS)}
    for name in CONDITIONS:
        np.testing.assert_array_equal(again[name].image, results[name].image, err_msg=name)
        np.testing.assert_array_equal(again[name].labels, results[name].labels, err_msg=name)
        np.testing.assert_array_equal(again[name].instances, results[name].instances, err_msg=name)


@pytest.mark.slow
def test_labels_contain_the_scene_and_the_placed_objects(rendered):
    _, results, _ = rendered
    res = results[CONDITIONS[0]]
    present = set(np.unique(res.labels).tolist())
    assert {ROAD, SKY, BUILDING, CAR} <= present, present
    car = res.instances == 1
    assert car.sum() > 20 and (res.labels[car] == CAR).all()
    # 12 m ahead in the ego lane: centred horizontally, below the horizon
    ys, xs = np.nonzero(car)
    assert abs(xs.mean() - 48) < 10 and ys.mean() > 24
    person = res.instances == 2
    assert person.any() and (res.labels[person] == PERSON).all()
    assert set(np.unique(res.instances).tolist()) == {0, 1, 2}
    assert (res.labels[res.instances == 0] != CAR).all()
    assert res.state["objects"][0]["category"] == "car"


@pytest.mark.slow
def test_the_label_pass_measures_the_distance_of_every_pixel(rendered):
    """Green channel of the label pass: the camera distance (View Distance), the same in every condition,
    inf for the sky; the placed car 12 m ahead is about 12 m away (its rear is nearer, its roof farther)."""
    _, results, _ = rendered
    ref = results[CONDITIONS[0]]
    assert ref.distance.shape == (48, 96) and ref.distance.dtype == np.float32
    sky = ref.labels == SKY
    assert np.isinf(ref.distance[sky]).all() and np.isfinite(ref.distance[~sky]).all()
    car = ref.instances == 1
    assert 9.0 < float(np.median(ref.distance[car])) < 14.0
    road = ref.labels == ROAD
    rows = np.nonzero(road)[0]  # the road recedes: lower rows are nearer
    near, far = road & (np.arange(48)[:, None] > np.percentile(rows, 80)), road & (np.arange(48)[:, None] < np.percentile(rows, 20))
    assert np.median(ref.distance[near]) < np.median(ref.distance[far])
    for name in CONDITIONS[1:]:
        np.testing.assert_array_equal(results[name].distance, ref.distance, err_msg=name)


@pytest.mark.slow
def test_a_blender_fog_ladder_writes_maps_that_follow_the_images(tmp_path):
    """One scene of the fog ladder through the CLI: the images lose contrast step by step and each
    condition's transmittance map is exp(-3.912 d / V) of the same distances."""
    from PIL import Image

    from pairedgta.testing.cli import base_overrides, run_cli

    proc = run_cli(base_overrides(tmp_path) + [
        "conditions=fog_ladder", "stages=[generate]", "generate.num_scenes=1", "renderer.width=96", "renderer.height=48",
        "renderer.samples=1", "tracking.enabled=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    scene, = (tmp_path / "cache" / "generate").glob("*/scenes/*")
    steps = ["Day-EXTRASUNNY", "Day-FOG-1000m", "Day-FOG-600m", "Day-FOG-300m", "Day-FOG-150m", "Day-FOG-75m"]
    contrast = [np.asarray(Image.open(scene / f"{c}.png")).mean(axis=2).std() for c in steps[1:]]
    assert contrast == sorted(contrast, reverse=True), contrast
    t = {c: np.asarray(Image.open(scene / f"{c}_transmittance.png")) / 65535.0 for c in steps}
    assert (t["Day-EXTRASUNNY"] == 1.0).all()
    ok = (t["Day-FOG-600m"] > 0.6) & (t["Day-FOG-600m"] < 0.99)  # 75 m: T^8 still above 16-bit resolution
    assert ok.sum() > 100
    for c, v in (("Day-FOG-300m", 300.0), ("Day-FOG-75m", 75.0)):
        np.testing.assert_allclose(np.log(np.maximum(t[c][ok], 1e-9)), np.log(t["Day-FOG-600m"][ok]) * 600.0 / v,
                                   rtol=0.02, atol=2e-4 * 600.0 / v)


@pytest.mark.slow
def test_the_sky_behind_thin_haze_is_the_haze_as_its_transmittance_map_says():
    """Light haze (20 km visibility: exp(-0.0002 d)) leaves near objects almost clear, but the sky lies
    behind an unbounded path: its map says transmittance 0 (distance inf), so the image shows the fog's
    own colour there, uniform, with none of the sky's gradient or clouds left (the mist pass once saturated
    at 2 km and kept 68 % of this sky)."""
    d = _descriptor()
    haze = dataclasses.replace(GRID["Day-EXTRASUNNY"], name="Day-HAZE", visibility_m=20000.0, cloud_cover=0.6)
    with BlenderRenderer(width=96, height=48, samples=2, town=TOWN) as r:
        clear = r.render(d, dataclasses.replace(haze, name="Day-CLOUDY", visibility_m=None))
        hazy = r.render(d, haze)
    sky = np.isinf(hazy.distance)
    inner = sky.copy()  # away from silhouettes, whose pixels mix sky and geometry samples
    for axis in (0, 1):
        for shift in (1, -1):
            inner &= np.roll(sky, shift, axis=axis)
    assert inner.sum() > 50
    assert clear.image[inner].astype(float).std(axis=0).max() > 3.0  # the clear sky has a gradient and clouds
    assert hazy.image[inner].astype(float).std(axis=0).max() <= 1.0  # the hazy one is the fog colour only


@pytest.mark.slow
def test_physical_order_of_conditions(rendered):
    _, results, _ = rendered
    day, fog, night = (results[n].image.astype(float) for n in ("Day-EXTRASUNNY", "Day-FOGGY", "Night-RAIN"))
    lum = lambda im: im.mean(axis=2)
    assert lum(night).mean() < lum(day).mean()
    assert lum(fog).std() < lum(day).std()  # fog lowers contrast


@pytest.mark.slow
def test_both_fog_models_light_clear_skies_alike_and_fog_the_same_scene():
    """fog_model=volume keeps a scattering box over the town; switched off under a clear sky it must
    let the sun through (an empty box shader once shadowed it), so both models give one clear
    image. Under fog both lower contrast with the same labels."""
    d = _descriptor()
    out = {}
    for model in ("analytic", "volume"):
        with BlenderRenderer(width=96, height=48, samples=2, town=TOWN, fog_model=model) as r:
            out[model] = {n: r.render(d, GRID[n]) for n in ("Day-EXTRASUNNY", "Day-FOGGY")}
    clear = [out[m]["Day-EXTRASUNNY"].image.astype(float) for m in ("analytic", "volume")]
    assert abs(clear[0].mean() - clear[1].mean()) < 3.0, (clear[0].mean(), clear[1].mean())
    road = out["analytic"]["Day-EXTRASUNNY"].labels == ROAD
    assert abs(clear[0][road].mean() - clear[1][road].mean()) < 4.0
    # the distance is the camera's, not a ray's last segment: the volume box's surface changes nothing
    np.testing.assert_allclose(out["volume"]["Day-EXTRASUNNY"].distance, out["analytic"]["Day-EXTRASUNNY"].distance,
                               rtol=1e-5)
    for model in ("analytic", "volume"):
        fogged = out[model]["Day-FOGGY"]
        np.testing.assert_array_equal(fogged.labels, out[model]["Day-EXTRASUNNY"].labels)
        assert fogged.image.mean(axis=2).std() < out[model]["Day-EXTRASUNNY"].image.mean(axis=2).std(), model
        assert fogged.state["fog_model"] == model


@pytest.mark.slow
def test_all_nine_paper_conditions_pair_at_very_low_resolution():
    d = _descriptor()
    r = BlenderRenderer(width=48, height=24, samples=1, denoise=False, town=TOWN, labels_per_condition=True)
    with r:
        results = [r.render(d, c) for c in GRID]
    assert len(results) == 9
    for res in results[1:]:
        np.testing.assert_array_equal(res.labels, results[0].labels)
        np.testing.assert_array_equal(res.instances, results[0].instances)
    images = {res.image.tobytes() for res in results}
    assert len(images) == 9


@pytest.mark.slow
def test_bad_scenes_are_one_line_renderer_errors():
    r = BlenderRenderer(width=32, height=16, samples=1, denoise=False, town=TOWN)
    region = ProceduralTownRegion(**TOWN)
    with r:
        # ego inside a block instead of on a road
        c = region.road_centres
        mid = float((c[0] + c[1]) / 2)
        with pytest.raises(RendererError, match="not a road") as err:
            r.prepare(_descriptor(location=Location(x=mid, y=mid)))
        assert "\n" not in str(err.value)
        # camera pushed into a building
        solids = region.layout().solids
        bx, by, bz = (float(v) for v in solids[int(np.argmax(solids[:, 5]))][:3])  # the tallest: a building
        road_x = float(c[np.argmin(np.abs(c - bx))]) + region.road_width / 4
        ego = Location(x=road_x, y=by, heading=0.0)
        with pytest.raises(RendererError, match="inside a building"):
            r.prepare(_descriptor(location=ego, camera=CameraPose(x=bx - road_x, y=0.0, z=bz + 2.0)))
        # unknown category (the descriptor refuses it too; a hand-built object must still fail cleanly)
        bad = DynamicObject("car", "x", forward=10.0, right=0.0)
        object.__setattr__(bad, "category", "tank")
        with pytest.raises(RendererError, match="category 'tank'"):
            r.prepare(_descriptor(objects=(bad,)))
        # a good scene still renders after the errors
        res = r.render(_descriptor(), GRID["Day-EXTRASUNNY"])
        assert res.image.shape == (16, 32, 3)


@pytest.mark.slow
def test_a_scene_renders_the_same_first_in_a_fresh_renderer_or_after_another_scene():
    """Resume safety (issue 16): a scene rendered right after a different scene (other objects,
    other place) matches the same scene rendered first by a fresh renderer, byte for byte."""
    k = _descriptor()
    loc = ProceduralTownRegion(**TOWN).sample_location(np.random.default_rng(7))
    j = _descriptor(scene_id="j", location=loc, objects=(
        DynamicObject("truck", "mule", forward=15.0, right=0.0, color=(20, 120, 40)),
        DynamicObject("bus", "bus", forward=28.0, right=0.0, heading=180.0),
        DynamicObject("rider", "a_m_y_motox_01", forward=8.0, right=1.0),
    ))
    conditions = [GRID["Day-EXTRASUNNY"], GRID["Night-RAIN"], GRID["Sunset-FOGGY"]]
    opts = {"width": 128, "height": 64, "samples": 1, "town": TOWN}
    with BlenderRenderer(**opts) as r:
        r.render(j, conditions[0])
        after = [r.render(k, c) for c in conditions]
    with BlenderRenderer(**opts) as r:
        alone = [r.render(k, c) for c in conditions]
    for c, a, b in zip(conditions, after, alone):
        assert a.image.tobytes() == b.image.tobytes(), (
            c.name, float(np.abs(a.image.astype(int) - b.image).mean()))
        np.testing.assert_array_equal(a.labels, b.labels)


# ---- the populated world ------------------------------------------------------------------

POPULATION = {"parked_cars_per_100m": 12.0, "lane_vehicles_per_100m": 4.0, "heavy_share": 0.1,
              "pedestrians_per_100m": 14.0, "crossing_pedestrians": 1.5, "cyclists_per_100m": 1.0,
              "motorcyclists_per_100m": 1.0, "parked_two_wheelers_per_100m": 1.0, "radius": 60.0}
POP_TOWN = {**TOWN, "population": POPULATION}


def _populated(seed: int = 2) -> SceneDescriptor:
    region = ProceduralTownRegion(**POP_TOWN)
    d = _descriptor(location=region.sample_location(np.random.default_rng(seed)), extra=(("town", POP_TOWN),))
    return region.populate(d)


@pytest.fixture(scope="module")
def populated():
    d = _populated()
    with BlenderRenderer(width=128, height=64, samples=1, denoise=False, town=POP_TOWN,
                         labels_per_condition=True) as r:
        results = [r.render(d, c) for c in GRID]
    return d, results


@pytest.mark.slow
def test_population_labels_are_exact_and_identical_under_all_nine_conditions(populated):
    d, results = populated
    assert len(d.ambient) >= 15
    for res in results[1:]:
        np.testing.assert_array_equal(res.labels, results[0].labels)
        np.testing.assert_array_equal(res.instances, results[0].instances)
    assert len({res.image.tobytes() for res in results}) == 9
    labels, inst = results[0].labels, results[0].instances
    first = len(d.objects) + 1
    seen = set(np.unique(inst).tolist()) - {0}
    ambient_seen = {i for i in seen if i >= first}
    assert len(ambient_seen) >= 5, seen
    # every instance carries the class of its entity (riders: rider + their vehicle)
    want = {"car": {CAR}, "person": {PERSON}, "truck": {CLASS_NAMES.index("truck")},
            "bus": {CLASS_NAMES.index("bus")}, "bicycle": {CLASS_NAMES.index("bicycle")},
            "motorcycle": {CLASS_NAMES.index("motorcycle")},
            "rider": {CLASS_NAMES.index(c) for c in ("rider", "bicycle", "motorcycle")}}
    for i in ambient_seen:
        e = d.ambient[i - first]
        assert set(np.unique(labels[inst == i]).tolist()) <= want[e.category], (i, e)
    assert {CAR, PERSON} <= set(np.unique(labels).tolist())


@pytest.mark.slow
def test_a_saved_populated_descriptor_replays_to_the_same_images(populated, tmp_path):
    d, results = populated
    d.save(tmp_path / "descriptor.json")
    back = SceneDescriptor.load(tmp_path / "descriptor.json")
    with BlenderRenderer(width=128, height=64, samples=1, denoise=False, town=TOWN) as r:
        conditions = list(GRID)
        for k in (0, len(conditions) - 2):
            res = r.render(back, conditions[k])
            assert res.image.tobytes() == results[k].image.tobytes()
            np.testing.assert_array_equal(res.labels, results[k].labels)


@pytest.mark.slow
def test_the_motox_rider_rides_a_motorcycle():
    loc = ProceduralTownRegion(**TOWN).sample_location(np.random.default_rng(2))
    d = _descriptor(location=loc, objects=(DynamicObject("rider", "a_m_y_motox_01", forward=8.0, right=0.0,
                                                         heading=90.0, color=(200, 30, 30)),))
    with BlenderRenderer(width=96, height=48, samples=1, denoise=False, town=TOWN) as r:
        res = r.render(d, GRID["Day-EXTRASUNNY"])
    classes = set(np.unique(res.labels[res.instances == 1]).tolist())
    assert CLASS_NAMES.index("motorcycle") in classes and CLASS_NAMES.index("rider") in classes
    assert CLASS_NAMES.index("bicycle") not in classes


@pytest.mark.slow
def test_cycles_cuda_probe_stays_quiet_on_the_cpu_and_other_output_passes():
    """Choosing the denoiser makes Cycles probe CUDA; on a CPU machine its 'CUEW initialization failed'
    line must not reach the user, while everything else the block prints still does (fresh process:
    the probe runs once per process)."""
    code = ("from pairedgta.render.blender.renderer import BlenderRenderer\n"
            "from pairedgta.render.blender.cycles import quiet_cuda_probe\n"
            "import os\n"
            "r = BlenderRenderer(width=32, height=16, samples=1, denoise=True)\n"
            "r.open(); r.close()\n"
            "with quiet_cuda_probe(True):\n"
            "    os.write(1, b'kept line\\nCUEW initialization failed\\n')\n"
            "print('done')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "CUEW" not in proc.stdout + proc.stderr
    assert "kept line" in proc.stdout and proc.stdout.rstrip().endswith("done")


def test_a_stop_that_cycles_swallows_is_raised_between_images(tmp_path):
    """Ctrl-C/SIGTERM arriving while Cycles renders is raised inside Blender's Python RenderEngine
    callback, where Blender prints it and renders on; the signal handlers also record it, and the
    renderer raises it again as soon as the image is done."""
    import signal
    from types import SimpleNamespace

    from pairedgta import interrupt
    from pairedgta.errors import Terminated
    from pairedgta.render.blender.renderer import BlenderRenderer

    out = tmp_path / "x.png"
    scene = SimpleNamespace(render=SimpleNamespace(filepath=""))

    calls = []

    def render(write_still):  # what Blender does with an exception raised in Cycles' callback
        calls.append(1)
        if len(calls) == 1:
            try:
                interrupt.request(signal.SIGTERM)
                raise Terminated("stopped by SIGTERM")
            except BaseException:
                pass
        out.write_bytes(b"png")

    r = object.__new__(BlenderRenderer)
    r._bpy = SimpleNamespace(context=SimpleNamespace(scene=scene), ops=SimpleNamespace(render=SimpleNamespace(render=render)))
    r._tmp = str(tmp_path)
    try:
        with pytest.raises(Terminated, match="SIGTERM"):
            r._render_to(str(out))
        interrupt.clear()
        r._render_to(str(out))  # no request pending: renders on
        interrupt.request(signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            interrupt.check()
        interrupt.clear()
        # during a render the handlers only record (nothing is raised into Cycles); raised right after
        with pytest.raises(Terminated):
            with interrupt.deferred():
                assert interrupt.request(signal.SIGTERM) is True  # the handler returns without raising
        interrupt.clear()
        assert interrupt.request(signal.SIGTERM) is False  # outside a render the handler raises at once
    finally:
        interrupt.clear()
