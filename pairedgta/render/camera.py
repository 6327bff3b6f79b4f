"""The camera between the scene-referred render and the stored sRGB image (the `camera` config group).

Why a model at all: a scene lit by street lamps is some 10 EV darker than one in the noon sun, and no camera
undoes that. GTA V's frames keep a night at about an eighth of the clean image's luma
(`pairedgta/data/gta_photometry.csv`); a renderer that exposes every condition to the same brightness
measures a shift that is not night. So the camera has an auto-exposure with physical limits: it undoes a
share (`compensation`) of the light level's change, within the EV range the sensor can add
(`ev_min`..`ev_max`); the rest stays in the image. Sensor noise (optional) is added to the exposed linear
signal before the tone curve, so it grows with the gain as a real sensor's does, from a seed of (scene,
condition): pairs stay exact and reruns byte-identical. The tone curve is the backend's view transform
(Blender's AgX through OpenColorIO).

Presets: `camera=gta` (the default, calibrated against the GTA V frames by
`+experiment=photometric_calibration`) and `camera=fixed` (one exposure for every condition: the pure
physical shift).
"""
from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.errors import ConfigError

MODES = ("auto", "fixed")


@dataclasses.dataclass(frozen=True)
class Camera:
    name: str = "gta"
    mode: str = "auto"              # auto: metered from the light level; fixed: `ev` for every condition
    ev: float = 0.277               # EV at the reference light level (auto) or always (fixed)
    light_reference: float = 4.696  # the light level (lighting()'s `light_level`) at which auto gives `ev`
    compensation: float = 0.5       # share of the light level's change (in EV) that auto-exposure undoes
    ev_min: float = -0.5            # the EV range auto-exposure may add to `ev` (what the sensor can compensate)
    ev_max: float = 2.0
    bias: float = 0.0               # added to every exposure (EV)
    overrides: Mapping[str, float] = dataclasses.field(default_factory=dict)  # EV per condition or time name
    view_transform: str = "AgX"
    look: str = "None"
    read_noise: float = 0.0         # std of the read noise, in linear units of the exposed image, at unit gain
    shot_noise: float = 0.0         # photon noise: variance = shot_noise * exposed signal * gain
    noise_seed: int = 0

    @classmethod
    def from_cfg(cls, cfg: Mapping[str, Any] | None) -> Camera:
        cfg = dict(cfg or {})
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ConfigError(f"camera: unknown key(s) {', '.join(unknown)}; known keys: {', '.join(sorted(known))}")
        try:
            values = {k: (dict(v) if k == "overrides" else v) for k, v in cfg.items()}
            cam = cls(**values)
            overrides = {str(k): float(v) for k, v in cam.overrides.items()}
            numbers = {f: float(getattr(cam, f)) for f in ("ev", "light_reference", "compensation", "ev_min",
                                                          "ev_max", "bias", "read_noise", "shot_noise")}
            cam = dataclasses.replace(cam, overrides=overrides, noise_seed=int(cam.noise_seed), **numbers)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"camera: {exc}; numbers expected (see pairedgta/conf/camera/gta.yaml)") from None
        checks = (
            ("mode", cam.mode in MODES, " or ".join(MODES)),
            ("light_reference", cam.light_reference > 0, "> 0"),
            ("compensation", 0.0 <= cam.compensation <= 1.0, "within 0..1 (1: the light level fully undone)"),
            ("ev_max", cam.ev_min <= cam.ev_max, f">= camera.ev_min ({cam.ev_min})"),
            ("read_noise", cam.read_noise >= 0, ">= 0"), ("shot_noise", cam.shot_noise >= 0, ">= 0"),
        )
        for key, ok, want in checks:
            if not ok:
                raise ConfigError(f"camera.{key}={getattr(cam, key)} is invalid; set it {want}")
        if not all(math.isfinite(v) for v in (cam.ev, cam.bias, cam.ev_min, cam.ev_max, *cam.overrides.values())):
            raise ConfigError("camera: ev, bias, ev_min, ev_max and overrides must be finite numbers")
        return cam

    # ---- exposure -----------------------------------------------------------------------------
    def auto_ev(self, light_level: float) -> float:
        """The EV auto-exposure adds for this light level, within the sensor's range."""
        if self.mode == "fixed":
            return 0.0
        wanted = self.compensation * math.log2(self.light_reference / max(float(light_level), 1e-6))
        return float(np.clip(wanted, self.ev_min, self.ev_max))

    def exposure(self, condition: Any, light_level: float) -> float:
        """The exposure (EV) of the image of `condition`: an override by condition or time name, else
        `ev` plus auto-exposure; `bias` on top of either."""
        if condition.name in self.overrides:
            ev = self.overrides[condition.name]
        elif condition.time in self.overrides:
            ev = self.overrides[condition.time]
        else:
            ev = self.ev + self.auto_ev(light_level)
        return ev + self.bias

    def gain(self, ev: float) -> float:
        """Analog gain over the sensor's base sensitivity: exposure beyond `ev` is amplification, which is
        what amplifies the read noise (a darker scene is a noisier image)."""
        return 2.0 ** max(ev - self.ev, 0.0)

    # ---- noise ------------------------------------------------------------------------------
    @property
    def noisy(self) -> bool:
        return self.read_noise > 0 or self.shot_noise > 0

    def seed_for(self, scene_seed: int, condition_name: str) -> int:
        """One noise seed per (noise seed, scene, condition): a pair's images get independent noise, and
        the same scene and condition the same noise in every run and shard."""
        return zlib.crc32(f"{self.noise_seed}:{int(scene_seed)}:{condition_name}".encode())

    def add_noise(self, linear: np.ndarray, ev: float, seed: int) -> np.ndarray:
        """Sensor noise on a linear (scene-referred, unexposed) H x W x 3 image: Gaussian with the
        variance of photon noise on the exposed signal plus read noise, both scaled by the gain;
        returned unexposed again, so the tone step applies the exposure as without noise."""
        if not self.noisy:
            return linear
        scale = 2.0 ** ev
        exposed = np.maximum(linear.astype(np.float64) * scale, 0.0)
        g = self.gain(ev)
        std = np.sqrt(self.shot_noise * exposed * g + (self.read_noise * g) ** 2)
        rng = np.random.default_rng(seed)
        noisy = np.maximum(exposed + rng.standard_normal(exposed.shape) * std, 0.0)
        return (noisy / scale).astype(np.float32)

    def describe(self) -> str:
        if self.mode == "fixed":
            return f"camera '{self.name}': fixed exposure {self.ev + self.bias:+.2f} EV"
        return (f"camera '{self.name}': auto-exposure undoing {self.compensation:.0%} of the light level's change, "
                f"{self.ev_min:+.1f}..{self.ev_max:+.1f} EV around {self.ev:+.2f} EV")


__all__ = ["Camera", "MODES"]
