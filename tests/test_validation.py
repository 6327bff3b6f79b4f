"""Automated pair validation: structure agreement and entity states."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pairedgta.testing.deepgtav_server import GameState, SyntheticView
from pairedgta.scene.descriptor import DynamicObject, Location, SceneDescriptor
from pairedgta.scene.validation import (
    DEFAULT_THRESHOLD,
    entity_mismatches,
    joaat,
    model_key,
    object_world_xy,
    structure_agreement,
    validate_group,
)


def blocks_picture(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    """A picture of random overlapping rectangles and a smooth background gradient."""
    rng = np.random.default_rng(seed)
    yy = np.mgrid[0:h, 0:w][0]
    img = np.empty((h, w, 3), np.float32)
    img[:] = (60 + 80 * yy / h)[..., None]
    for _ in range(25):
        y0, x0 = rng.integers(0, h - 10), rng.integers(0, w - 10)
        y1, x1 = y0 + rng.integers(5, h // 2), x0 + rng.integers(5, w // 2)
        img[y0:y1, x0:x1] = rng.uniform(20, 235, 3)
    return img.astype(np.uint8)


def darken(img: np.ndarray, gain: float, noise: float = 0.0, seed: int = 1) -> np.ndarray:
    out = img.astype(np.float32) * gain * np.array([0.75, 0.85, 1.0], np.float32)  # bluish night
    out += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def fog(img: np.ndarray, amount: float) -> np.ndarray:
    h = img.shape[0]
    f = amount * (1.0 - np.linspace(0.0, 0.6, h))[:, None, None]  # denser towards the horizon
    out = img.astype(np.float32) * (1 - f) + 185.0 * f
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def street(x: float, y: float, heading: float, hour: int = 12, weather: str = "EXTRASUNNY") -> np.ndarray:
    return SyntheticView().render(GameState(x=x, y=y, heading=heading, hour=hour, weather=weather, width=192, height=108))


# --------------------------------------------------------------------------- structure


def test_same_picture_darkened_or_fogged_agrees():
    ref = blocks_picture(0)
    variants = {
        "ref": ref,
        "night": darken(ref, 0.12, noise=1.5),
        "dusk": darken(ref, 0.4, noise=1.0),
        "fog": fog(ref, 0.65),
        "night-fog": fog(darken(ref, 0.2, noise=1.0), 0.5),
    }
    g = validate_group(variants, "ref")
    assert g.ok, g.reasons
    assert g.structure["ref"] == 1.0
    for name in ("night", "dusk", "fog", "night-fog"):
        assert g.structure[name] > 0.8, (name, g.structure[name])


def test_different_picture_disagrees():
    ref = blocks_picture(0)
    g = validate_group(
        {"ref": ref, "other": blocks_picture(1), "other-dark": darken(blocks_picture(2), 0.3),
         "shifted": np.roll(ref, 6, axis=1), "flipped": ref[::-1].copy()},
        "ref",
    )
    assert not g.ok
    for name in ("other", "other-dark", "shifted", "flipped"):
        assert g.structure[name] < 0.4, (name, g.structure[name])
        assert any(r.startswith(f"{name}: structure agreement") for r in g.reasons)


def test_street_views_same_scene_vs_other_scene():
    day = street(100, 200, 0)
    same = {"night": street(100, 200, 0, 23, "RAIN"), "fog": street(100, 200, 0, 19, "FOGGY")}
    for img in same.values():
        assert structure_agreement(day, img) > 0.95
    # the synthetic streets share their road layout, so another scene still agrees a little
    for xyh in [(900, -300, 90), (-700, 50, 180)]:
        assert structure_agreement(day, street(*xyh)) < DEFAULT_THRESHOLD


def test_size_mismatch_and_blank_reference():
    ref = blocks_picture(3)
    g = validate_group({"ref": ref, "small": ref[:60, :80]}, "ref")
    assert not g.ok and math.isnan(g.structure["small"])
    assert g.reasons == ["small: size 80x60 differs from reference 160x120"]
    blank = np.zeros((40, 50, 3), np.uint8)
    g = validate_group({"ref": blank, "v": blocks_picture(4)[:40, :50]}, "ref")
    assert not g.ok and "almost no edges" in g.reasons[0]
    g = validate_group({"a": ref}, "missing")
    assert not g.ok and "reference condition 'missing'" in g.reasons[0]


def test_grayscale_and_float_images_are_accepted():
    ref = blocks_picture(5)
    gray = ref.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    assert structure_agreement(np.round(gray).astype(np.uint8), ref) > 0.95
    assert structure_agreement(ref.astype(np.float32) / 255.0, darken(ref, 0.3)) > 0.9


# --------------------------------------------------------------------------- entity states

DESC = SceneDescriptor(
    "s1", 1, Location(100.0, -200.0, 25.0, heading=90.0),
    objects=(
        DynamicObject("car", "blista", forward=10.0, right=2.0),
        DynamicObject("motorcycle", "bati", forward=15.0, right=-1.0),
        DynamicObject("person", "a_m_y_hipster_01", forward=6.0, right=4.0),
    ),
)


def spawned_state(**changes) -> dict:
    """The state a faithful backend reports for DESC (world positions, ped model as hex hash)."""
    cx, cy = object_world_xy(DESC, DESC.objects[0])
    mx, my = object_world_xy(DESC, DESC.objects[1])
    px, py = object_world_xy(DESC, DESC.objects[2])
    state = {
        "location": [100.0, -200.0, 25.0],
        "vehicles": [
            {"model": "blista", "classID": 0, "position": [cx, cy, 25.0], "spawned": True},
            {"model": "bati", "classID": 1, "position": [mx, my, 25.0], "spawned": True},
        ],
        "peds": [{"model": f"0x{joaat('a_m_y_hipster_01'):08x}", "position": [px, py, 25.0], "spawned": True}],
    }
    state.update(changes)
    return state


def test_object_world_xy_uses_gta_heading():
    # heading 90 = facing west (-x); right of a west-facing car is north (+y)
    assert object_world_xy(DESC, DESC.objects[0]) == pytest.approx((90.0, -198.0))
    assert model_key("a_m_y_hipster_01") == model_key("0x2307A353") == joaat("A_M_Y_HIPSTER_01")
    assert joaat("adder") == 0xB779A091


def test_matching_states_pass():
    img = blocks_picture(6)
    g = validate_group({"a": img, "b": darken(img, 0.3)}, "a", DESC, {"a": spawned_state(), "b": spawned_state()})
    assert g.ok, g.reasons


def test_moved_missing_extra_and_wrong_entities_are_reported():
    moved = spawned_state()
    moved["vehicles"][0]["position"][0] += 3.0
    assert any("car 'blista' expected at (90.0, -198.0)" in r for r in entity_mismatches(DESC, moved))

    missing = spawned_state(peds=[])
    reasons = entity_mismatches(DESC, missing)
    assert len(reasons) == 1 and reasons[0].startswith("person 'a_m_y_hipster_01' expected at (94.0, -196.0)")

    extra = spawned_state()
    extra["vehicles"].append({"model": "bus", "position": [0.0, 0.0, 0.0], "spawned": True})
    assert entity_mismatches(DESC, extra) == ["3 spawned vehicles reported, descriptor has 2"]

    wrong_model = spawned_state()
    wrong_model["vehicles"][1]["model"] = "akuma"
    assert any("motorcycle 'bati'" in r for r in entity_mismatches(DESC, wrong_model))

    wrong_class = spawned_state()
    wrong_class["vehicles"][1]["classID"] = 0
    assert any("motorcycle 'bati'" in r for r in entity_mismatches(DESC, wrong_class))

    far_ego = spawned_state(location=[140.0, -200.0, 25.0])
    assert any("ego reported at (140.0, -200.0), 40.0 m" in r for r in entity_mismatches(DESC, far_ego))

    img = blocks_picture(7)
    g = validate_group({"a": img, "b": img}, "a", DESC, {"a": spawned_state(), "b": moved})
    assert not g.ok and all(r.startswith("b: ") for r in g.reasons)


def test_classic_state_format_and_ambient_traffic():
    cx, cy = object_world_xy(DESC, DESC.objects[0])
    mx, my = object_world_xy(DESC, DESC.objects[1])
    classic = {
        "vehicles": [  # box corners, no model, no spawned flag; plus an ambient car
            {"FUR": [cx + 1, cy + 2, 26.0], "BLL": [cx - 1, cy - 2, 24.0], "classID": 0},
            {"FUR": [mx + 0.5, my + 1, 26.0], "BLL": [mx - 0.5, my - 1, 24.0], "classID": 1},
            {"FUR": [300.0, 300.0, 26.0], "BLL": [298.0, 296.0, 24.0], "classID": 0},
        ],
    }
    assert entity_mismatches(DESC, classic) == []  # peds not reported: not checked
    classic["vehicles"].pop(1)
    assert any("motorcycle 'bati'" in r for r in entity_mismatches(DESC, classic))


def test_state_that_is_not_an_object():
    img = blocks_picture(8)
    g = validate_group({"a": img}, "a", DESC, {"a": ["not", "a", "dict"]})  # type: ignore[dict-item]
    assert not g.ok and g.reasons == ["a: backend state is list, not a JSON object"]


@pytest.mark.slow
def test_a_validation_module_that_fails_to_import_is_one_line_before_any_render(tmp_path, monkeypatch):
    """A broken install once made every scene pass unchecked ({"ok": True, "reasons": ["validation
    unavailable"]}); now `python -m pairedgta` stops with one line naming the module and the fix, and no
    scene is rendered or kept."""
    import sys

    from pairedgta.testing.cli import fast_overrides, run_cli

    monkeypatch.setitem(sys.modules, "pairedgta.scene.validation", None)  # `import` of it raises ImportError
    proc = run_cli(fast_overrides(tmp_path) + ["stages=[generate]"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr[-2000:]
    assert "pairedgta.scene.validation" in errors[0] and "pip install -e ." in errors[0], errors[0]
    assert "generate.validation.enabled=false" in errors[0]
    assert "Traceback" not in proc.stderr
    generated = tmp_path / "cache" / "generate"
    assert not list(generated.glob("[!.]*")) if generated.exists() else True  # no dataset entry
    assert not list(generated.glob(".partial-*/scenes/[!.]*")) if generated.exists() else True  # no scene rendered
    # with validation off the same install renders (the escape the message offers is real)
    proc = run_cli(fast_overrides(tmp_path) + ["stages=[generate]", "generate.validation.enabled=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
