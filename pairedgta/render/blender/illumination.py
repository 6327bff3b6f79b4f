"""Illumination: what a condition's sun, sky, clouds, rain and fog mean as render parameters.

`lighting(cond)` is pure numpy, continuous in every physical field, and shared with the camera's
exposure (render/camera.py) and the tests; shading.py turns its output into knob values and light
energies.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.conditions import Condition

FOG_ALBEDO = 0.92
# weights of the in-scattered light of the analytic fog, matched to the volume model's far field
FOG_SKY, FOG_SUN = 0.7, 0.2
# Artificial light, relative to the sun (strength 4.5): a street-lit road is thousands of times darker than
# a sunlit one (10-30 lx against 50,000 lx and more), and a camera undoes only part of that
# (render/camera.py). The light sources themselves (lamp heads, head-lights) stay bright: they are what a
# night image shows and what fog glows around. Lit windows glow as dimly as interiors do from outside.
LAMP_POWER = 40.0        # W per street-lamp spot light
HEADLIGHT_POWER = 30.0   # W per head-light spot light
WINDOW_EMISSION = 0.08   # emission strength of a lit window
FILL_COLOUR = (1.0, 0.82, 0.62)  # the city's diffuse light: mostly sodium and warm-white lamps, reflected


@dataclasses.dataclass(frozen=True)
class NightLight:
    """The light of a street at night, the part of the light model fitted to GTA V's night frames
    (`experiments/fit_night_light.py`, `renderer.night`). A look, not a measurement: GTA V's nights are lit by a
    strong diffuse fill relative to their light sources, and a camera of fixed exposure that sees our physical
    sources (lamp heads, head-light lenses and their reflections on a wet road, lit windows and shop fronts, far
    brighter than the street around them) keeps three times GTA V's contrast. Each term applies at night only, weighted by the `night` weight
    of the sun's elevation (0 from 2 degrees up, 1 below -8), so day and sunset images keep every pixel:

    - `fill`: radiance of the city's diffuse light, what a street lit by lamps every 28 m, lit windows and shop
      fronts, and the glow of the sky above them send into every shadow after many bounces: a two-bounce path
      tracer misses it (the scene's second bounce is an ambient-occlusion estimate of the sky), GTA V adds it as
      an ambient term. It lights the scene through the world shader's non-camera rays (the sky the camera sees
      stays the night sky) and the wet road reflects it.
    - `lamps`, `headlights`, `windows`: the power at night of the street lamps (spot light and lamp head), of
      the vehicles' head lights (spot light and lens; tail lights follow) and the emission of lit windows and
      shop fronts, as factors on LAMP_POWER, HEADLIGHT_POWER and WINDOW_EMISSION (1: the physical model's)."""

    # fitted by `python experiments/fit_night_light.py` (16 scenes of seeds 2 and 3, 256x128: its docstring);
    # pairedgta/conf/renderer/blender.yaml `night` says the same
    fill: float = 0.035
    lamps: float = 0.5
    headlights: float = 0.03
    windows: float = 0.1

    @classmethod
    def from_cfg(cls, cfg: Mapping[str, Any] | None) -> NightLight:
        return _light_from_cfg(cls, "renderer.night", cfg)


@dataclasses.dataclass(frozen=True)
class SunsetLight:
    """The light of a low sun under cloud and haze, the part of the light model fitted to GTA V's sunset frames
    (`experiments/fit_sunset_light.py`, `renderer.sunset`). The clear sunset is the sky model's; what it leaves
    open is how dark a cloud deck and how bright fog are when the sun is a few degrees up: sunlight crosses the
    deck on a slant path many times its noon length, and haze lit from the horizon glows toward the camera
    (forward scattering) instead of the isotropic share of the noon model. Each term applies weighted by the
    `dusk` weight of the sun's elevation (1 with the sun 2 to 4 degrees up; 0 from 25 degrees up and, as the night
    weight takes over, from 8 degrees down), so day and night images keep every pixel (a clear sunset's too):

    - `overcast`: factor on the sun's light through a full cloud cover and on the cloud base's own light (the
      sky of an overcast image, the light it sends into the scene and into the haze), scaled by the cover
      (`cloud_cover`, or the rain's level): a clear sky is unchanged, rain's 0.9 cover nearly fully.
    - `haze`: factor on the light that fog and rain haze scatter toward the camera (the analytic fog's colour)."""

    # fitted by `python experiments/fit_sunset_light.py` (its docstring); pairedgta/conf/renderer/blender.yaml
    # `sunset` says the same
    overcast: float = 0.4
    haze: float = 1.8

    @classmethod
    def from_cfg(cls, cfg: Mapping[str, Any] | None) -> SunsetLight:
        return _light_from_cfg(cls, "renderer.sunset", cfg)


def _light_from_cfg(cls, where: str, cfg: Mapping[str, Any] | None):
    """A fitted light's dataclass from its config mapping: known keys, numbers >= 0, one-line errors."""
    from pairedgta.errors import ConfigError

    cfg = dict(cfg or {})
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(cfg) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; known keys: {', '.join(known)}")
    try:
        light = cls(**{k: float(v) for k, v in cfg.items()})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: numbers expected ({exc})") from None
    for key in known:
        value = getattr(light, key)
        if not (math.isfinite(value) and value >= 0.0):
            raise ConfigError(f"{where}.{key}={value} is invalid; set it to a number >= 0")
    return light


NIGHT = NightLight()  # the fitted night
SUNSET = SunsetLight()  # the fitted sunset
UNFITTED_SUNSET = SunsetLight(overcast=1.0, haze=1.0)  # the sky model's own (before the fit)
PHYSICAL = NightLight(fill=0.0, lamps=1.0, headlights=1.0, windows=1.0)  # the physical model's own (before the fit)


def _smoothstep(a: float, b: float, x: float) -> float:
    t = min(max((x - a) / (b - a), 0.0), 1.0)
    return t * t * (3 - 2 * t)


def sun_vector(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards the sun; azimuth clockwise from north (+y), east is +x."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])


def sun_transmittance(elevation_deg: float) -> np.ndarray:
    """RGB transmittance through the atmosphere (Kasten-Young air mass, Rayleigh-like optical
    depths): white at noon, orange near the horizon."""
    e = max(elevation_deg, -1.0)
    airmass = 1.0 / (math.sin(math.radians(max(e, 0.0))) + 0.50572 * (e + 6.07995) ** -1.6364)
    return np.exp(-np.array([0.06, 0.11, 0.24]) * airmass)


def lighting(cond: Condition, night_light: NightLight = NIGHT, sunset_light: SunsetLight = SUNSET) -> dict[str, Any]:
    """All condition-dependent render parameters; continuous in every physical field. The extinction
    is the condition's own (visibility and rain rate, conditions.py), so the image and the
    transmittance map written beside it attenuate alike. `light_level` is what the camera meters
    (render/camera.py): the light falling on the scene from the sun, the sky and, at night, the lamps and the
    city's diffuse light (`night_light`: NightLight); at a low sun, cloud and haze follow `sunset_light`."""
    el = float(cond.sun_elevation_deg)
    rain = cond.rain_level
    cloud = max(float(cond.cloud_cover), rain)
    wet = max(float(cond.wetness), rain)
    fog = cond.fog_level
    trans = sun_transmittance(el)
    sun_vis = _smoothstep(-1.0, 2.0, el)
    sun_color = trans / trans.max()
    sky = min(max((el + 6.0) / 36.0, 0.0), 1.0) ** 1.3  # daylight sky brightness
    warm = (1.0 - _smoothstep(0.0, 22.0, el)) * _smoothstep(-7.0, -1.0, el)
    night = 1.0 - _smoothstep(-8.0, 2.0, el)
    dusk = (1.0 - _smoothstep(4.0, 25.0, el)) * (1.0 - night)  # SunsetLight's weight: night + dusk = 1 below 4 deg
    # a cloud deck at a low sun (SunsetLight.overcast), in proportion to the cover
    under_cloud = 1.0 + (sunset_light.overcast - 1.0) * cloud * dusk
    sun_strength = 4.5 * sun_vis * float(trans.max()) * (1.0 - 0.92 * cloud) * under_cloud
    zenith = sky * ((1 - warm) * np.array([0.10, 0.24, 0.62]) + warm * np.array([0.08, 0.13, 0.34]))
    horizon = sky * ((1 - warm) * np.array([0.55, 0.64, 0.78]) + warm * np.array([1.1, 0.55, 0.28]))
    city_glow = np.array([0.012, 0.008, 0.005]) * night
    zenith = zenith + np.array([0.0015, 0.0025, 0.006]) * night
    horizon = horizon + city_glow
    glow = (0.9 * warm + 0.15) * sky * sun_color * (1 - cloud)
    # rain clouds are dark, and heavy rain's haze hides the city's glow from their base
    grey = (np.array([0.50, 0.52, 0.56]) * (sky * (1.0 - 0.85 * rain) + 0.006) * under_cloud
            + city_glow * (1.0 - 0.8 * rain))
    moon = 0.05 * night * (1.0 - 0.9 * cloud)  # a moonlit clear night is brighter than an overcast one
    lamps = 1.0 - _smoothstep(-3.0, 6.0, el)
    vehicle_lights = max(lamps, _smoothstep(0.2, 0.6, max(rain, fog)))
    sky_light = 2.6 * float(np.mean(zenith + horizon) / 2 * (1 - cloud) + np.mean(grey) * cloud)
    extinction = cond.extinction_per_m  # 1/m
    # radiance that fog and rain haze scatter toward the camera everywhere (renderer.fog_model=analytic):
    # albedo times the light arriving from the sky (cloud-grey as cover grows) and the sun (isotropic
    # share). Lamp and head-light light is scattered where it is: the compositor's glare gives each its
    # halo, so the night's fog stays dark away from the lights instead of glowing uniformly.
    # the city's diffuse light (NightLight.fill): lights the scene, not the sky the camera sees, nor the haze (the
    # lamps' light in the air is the glare around each lamp: scattering the fill too would count it twice)
    fill = night_light.fill * night * np.array(FILL_COLOUR)

    def at_night(factor: float) -> float:  # a NightLight factor, weighted by how much of the night it is
        return 1.0 + (factor - 1.0) * night
    ambient = (zenith + horizon) / 2 * (1 - cloud) + grey * cloud
    fog_color = FOG_ALBEDO * (FOG_SKY * ambient + FOG_SUN * sun_strength * sun_color / (4 * math.pi))
    fog_color = fog_color * (1.0 + (sunset_light.haze - 1.0) * dusk)  # haze lit from the horizon (SunsetLight.haze)
    light_level = (sun_strength * max(math.sin(math.radians(el)), 0.0) + sky_light + 0.04 * lamps
                   + 2.6 * float(np.mean(fill)))
    return {
        "sun_dir": sun_vector(el, cond.sun_azimuth_deg), "sun_strength": sun_strength, "sun_color": sun_color,
        "sun_angle_deg": 0.53 + 25.0 * cloud,
        "moon_dir": sun_vector(38.0, (cond.sun_azimuth_deg + 180.0) % 360.0), "moon_strength": moon,
        "zenith": zenith, "horizon": horizon, "glow": glow, "cloud_color": grey,
        "cloud_cover": cloud, "overcast": _smoothstep(0.55, 0.95, cloud),
        "wetness": wet, "puddle_threshold": 1.0 - 0.42 * wet,
        "fog": fog, "rain": rain, "extinction": extinction, "fog_color": fog_color,
        "lamps": lamps, "vehicle_lights": vehicle_lights,
        "window_lit": lamps, "light_level": light_level, "fill": fill,
        "night": night, "dusk": dusk,
        "lamp_power": LAMP_POWER * at_night(night_light.lamps) * lamps,
        "lamp_emit": 25.0 * at_night(night_light.lamps) * lamps,
        "headlight_power": HEADLIGHT_POWER * at_night(night_light.headlights) * vehicle_lights,
        "headlight_emit": 30.0 * at_night(night_light.headlights) * vehicle_lights,
        "taillight_emit": 0.3 + 10.0 * at_night(night_light.headlights) * vehicle_lights,
        "window_emit": WINDOW_EMISSION * at_night(night_light.windows) * lamps,
    }


__all__ = [
    "FILL_COLOUR",
    "HEADLIGHT_POWER",
    "LAMP_POWER",
    "NIGHT",
    "PHYSICAL",
    "SUNSET",
    "UNFITTED_SUNSET",
    "WINDOW_EMISSION",
    "NightLight",
    "SunsetLight",
    "lighting",
    "sun_transmittance",
    "sun_vector",
]
