"""The camera model (pairedgta/render/camera.py): auto-exposure within the sensor's EV range, presets, noise
seeding, bad values; no bpy needed."""
from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from pairedgta.conditions import build_condition_grid
from pairedgta.errors import ConfigError
from pairedgta.render.blender.illumination import lighting
from pairedgta.render.camera import Camera
from pairedgta.testing.cli import CONF, compose_cfg

GRID = build_condition_grid(OmegaConf.to_container(OmegaConf.load(CONF / "conditions" / "paper.yaml")))


def preset(name: str) -> Camera:
    return Camera.from_cfg(OmegaConf.to_container(compose_cfg([f"camera={name}"]).camera, resolve=True))


def exposures(cam: Camera) -> dict[str, float]:
    return {c.name: cam.exposure(c, lighting(c)["light_level"]) for c in GRID.conditions}


def test_the_default_camera_is_gta_and_reaches_the_renderer():
    cfg = compose_cfg([])
    assert cfg.camera.name == "gta"
    assert OmegaConf.to_container(cfg.renderer, resolve=True)["camera"]["name"] == "gta"
    assert compose_cfg(["camera=fixed"]).renderer.camera.mode == "fixed"


def test_auto_exposure_stays_within_the_sensors_range():
    cam = Camera(ev=0.3, light_reference=4.0, compensation=0.5, ev_min=-0.5, ev_max=1.5)
    assert cam.auto_ev(4.0) == 0.0
    assert cam.auto_ev(1.0) == pytest.approx(1.0)        # 2 EV darker, half of it undone
    assert cam.auto_ev(1e-6) == pytest.approx(1.5)       # a dark night: the rest stays in the image
    assert cam.auto_ev(1e6) == pytest.approx(-0.5)
    assert Camera(compensation=1.0, ev_max=10, light_reference=4.0).auto_ev(0.5) == pytest.approx(3.0)


def test_presets_gta_and_fixed():
    gta, fixed = exposures(preset("gta")), exposures(preset("fixed"))
    assert len(set(fixed.values())) == 1                 # one exposure for every condition
    # the clean image is the same under both: same exposure to a thousandth of an EV
    assert fixed["Day-EXTRASUNNY"] == pytest.approx(gta["Day-EXTRASUNNY"], abs=1e-3)
    # auto-exposure lifts darker conditions, never above its range
    cam = preset("gta")
    for name, ev in gta.items():
        assert cam.ev + cam.ev_min - 1e-9 <= ev <= cam.ev + cam.ev_max + 1e-9, name
    assert gta["Night-EXTRASUNNY"] >= gta["Day-EXTRASUNNY"]


def test_overrides_and_bias():
    cam = Camera.from_cfg({"overrides": {"Night": 1.0, "Day-RAIN": -1.0}, "bias": 0.5})
    assert cam.exposure(GRID["Night-FOGGY"], 0.01) == 1.5
    assert cam.exposure(GRID["Day-RAIN"], 0.01) == -0.5


def test_noise_is_seeded_per_scene_and_condition_and_grows_with_gain():
    cam = Camera(read_noise=0.002, shot_noise=0.001)
    img = np.full((32, 48, 3), 0.05, np.float32)
    a = cam.add_noise(img, 0.3, cam.seed_for(7, "Night-RAIN"))
    b = cam.add_noise(img, 0.3, cam.seed_for(7, "Night-RAIN"))
    c = cam.add_noise(img, 0.3, cam.seed_for(7, "Night-FOGGY"))
    d = cam.add_noise(img, 0.3, cam.seed_for(8, "Night-RAIN"))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c) and not np.array_equal(a, d)
    # the same exposed level from a 4x darker scene needs 2 EV more gain, which amplifies the noise
    low = np.std(cam.add_noise(img, 0.3, 1) * 2 ** 0.3)
    high = np.std(cam.add_noise(img / 4, 2.3, 1) * 2 ** 2.3)
    assert high > 1.5 * low
    assert Camera().add_noise(img, 0.3, 1) is img  # no noise configured: the image untouched


@pytest.mark.parametrize("cfg, key", [
    ({"mode": "manual"}, "camera.mode"),
    ({"compensation": 1.5}, "camera.compensation"),
    ({"ev_min": 1.0, "ev_max": 0.0}, "camera.ev_max"),
    ({"read_noise": -1}, "camera.read_noise"),
    ({"ev": "bright"}, "camera:"),
    ({"iso": 100}, "camera: unknown key"),
])
def test_bad_values_are_one_line_errors_naming_the_key(cfg, key):
    with pytest.raises(ConfigError) as err:
        Camera.from_cfg(cfg)
    assert key in str(err.value) and "\n" not in str(err.value)
