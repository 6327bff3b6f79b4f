"""2D corruptions of the clean image as conditions (ImageNet-C / Cityscapes-C / COCO-C: Hendrycks & Dietterich 2019,
Michaelis et al. 2019), through `imagecorruptions` (bethgelab, the implementation those benchmarks use).

A corruption condition is `C-<corruption>-<severity>` (C-fog-3): the clean condition's image run through one filter at
one severity. Nothing in the scene moves, so the clean image's labels, instance masks and boxes stay exact (the
dataset readers give it the clean condition's files); a 2D filter has no depth, so it has no transmittance (NaN).

Config (`conditions.corruptions`, pairedgta/conf/conditions/corruptions.yaml): `names` (a library subset such as
`common`, the 15, or a list), `only` (a subset of those), `severities` (1..5), `of` (the clean condition; null = the
set's reference). The names here are the library's; tests/test_corruptions.py checks they match it."""
from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import importlib.util
import sys
import types
import warnings
import zlib
from typing import Any, Iterator, Mapping

import numpy as np

from pairedgta.errors import ConfigError, PairedGTAError

PREFIX = "C"
LIBRARY = "imagecorruptions"
KEYS = ("names", "only", "severities", "of")
SEVERITIES = (1, 2, 3, 4, 5)
# the library's order (corruption_tuple) and subsets (get_corruption_names)
COMMON = ("gaussian_noise", "shot_noise", "impulse_noise", "defocus_blur", "glass_blur", "motion_blur", "zoom_blur",
          "snow", "frost", "fog", "brightness", "contrast", "elastic_transform", "pixelate", "jpeg_compression")
VALIDATION = ("speckle_noise", "gaussian_blur", "spatter", "saturate")
SUBSETS: dict[str, tuple[str, ...]] = {
    "common": COMMON, "validation": VALIDATION, "all": COMMON + VALIDATION, "noise": COMMON[0:3],
    "blur": COMMON[3:7], "weather": COMMON[7:11], "digital": COMMON[11:15],
}
SLOW = ("glass_blur", "zoom_blur")  # per-pixel Python loops / 10-30 zooms: experiments/bench_corruptions.py


def condition_name(corruption: str, severity: int) -> str:
    return f"{PREFIX}-{corruption}-{int(severity)}"


def parse_name(name: str) -> tuple[str, int] | None:
    """(corruption, severity) of a corruption condition's name, None for any other name."""
    parts = str(name).split("-")
    if len(parts) == 3 and parts[0] == PREFIX and parts[1] in SUBSETS["all"] and parts[2].isdigit():
        return parts[1], int(parts[2])
    return None


def _names(value: Any, key: str) -> list[str]:
    if isinstance(value, str):
        if value in SUBSETS:
            return list(SUBSETS[value])
        value = [value]
    if not isinstance(value, (list, tuple)) or not value:
        raise ConfigError(f"{key}={value!r}; use a subset ({', '.join(SUBSETS)}) or a list of corruption names")
    unknown = [str(v) for v in value if str(v) not in SUBSETS["all"]]
    if unknown:
        raise ConfigError(f"{key}: unknown corruption(s) {unknown}; use names of {LIBRARY}: "
                          f"{', '.join(SUBSETS['all'])}")
    return list(dict.fromkeys(str(v) for v in value))


def _severities(value: Any, key: str) -> list[int]:
    values = [value] if isinstance(value, (int, str)) else value
    if not isinstance(values, (list, tuple)) or not values:
        raise ConfigError(f"{key}={value!r}; use a list of severities in 1..5, e.g. [1, 3, 5]")
    out = []
    for v in values:
        if isinstance(v, bool) or not (isinstance(v, int) or (isinstance(v, str) and v.isdigit())) \
                or int(v) not in SEVERITIES:
            raise ConfigError(f"{key}: severity {v!r} is not one of 1..5 (the library's levels); "
                              "use a list such as [1, 3, 5]")
        out.append(int(v))
    return sorted(set(out))


def options(node: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The checked `conditions.corruptions` node: {names, severities, of} with `only` applied; None when unset."""
    if node is None or node is False:
        return None
    if isinstance(node, str) or isinstance(node, (list, tuple)):
        node = {"names": node}
    if not isinstance(node, Mapping):
        raise ConfigError(f"conditions.corruptions={node!r}; use a mapping {{names: common, severities: [1,2,3,4,5]}} "
                          "or null")
    unknown = sorted(set(node) - set(KEYS))
    if unknown:
        raise ConfigError(f"conditions.corruptions: unknown key(s) {unknown}; allowed: {', '.join(KEYS)}")
    names = _names(node.get("names", "common"), "conditions.corruptions.names")
    only = node.get("only")
    if only is not None:
        picked = _names(only, "conditions.corruptions.only")
        missing = [n for n in picked if n not in names]
        if missing:
            raise ConfigError(f"conditions.corruptions.only: {missing} not in conditions.corruptions.names "
                              f"({', '.join(names)}); add them to names (or names=all)")
        names = [n for n in names if n in picked]
    severities = _severities(node.get("severities", list(SEVERITIES)), "conditions.corruptions.severities")
    of = node.get("of")
    return {"names": names, "severities": severities, "of": None if of is None else str(of)}


def conditions(node: Mapping[str, Any] | None, rendered: list[Any], reference: str) -> list[Any]:
    """The corruption conditions of `node` over the clean condition among `rendered` (pairedgta.conditions.Condition),
    corruption by corruption, each at every severity."""
    from dataclasses import replace

    opts = options(node)
    if opts is None:
        return []
    clean_name = opts["of"] or reference
    clean = next((c for c in rendered if c.name == clean_name), None)
    if clean is None or clean.corruption is not None:
        where = "conditions.corruptions.of" if opts["of"] else "conditions.reference"
        raise ConfigError(f"{where}={clean_name!r}: corruptions need a rendered clean condition to corrupt, and the "
                          f"set has none of that name (it has {[c.name for c in rendered]}); set "
                          "conditions.corruptions.of to one of them, or choose conditions=corruptions")
    # the clean condition's light and weather, under a name of its own (checked as the clean one was)
    return [replace(clean, name=condition_name(n, s), corruption=n, severity=s, source=clean.name)
            for n in opts["names"] for s in opts["severities"]]


# -- the library, with its fixes for current numpy / SciPy / scikit-image / setuptools -------------------------------
_LIB: dict[str, Any] = {}


def _pkg_resources_shim() -> types.ModuleType:
    """imagecorruptions 1.1.2 imports pkg_resources.resource_filename (for frost's bundled photographs) at import;
    setuptools, which provides pkg_resources, is not installed in a plain venv of Python >= 3.12 and has deprecated
    it: this stands in with the same answer (a file beside the package's module) from importlib."""
    shim = types.ModuleType("pkg_resources")

    def resource_filename(package: str, resource: str) -> str:
        import os

        return os.path.join(os.path.dirname(sys.modules[package].__file__), resource)

    shim.resource_filename = resource_filename  # type: ignore[attr-defined]
    return shim


def _gaussian_compat(gaussian: Any) -> Any:
    """imagecorruptions 1.1.2 calls skimage.filters.gaussian(..., multichannel=True) (glass_blur, gaussian_blur);
    scikit-image removed `multichannel` in 0.21 (a TypeError): the same filter with channel_axis=-1, which is what
    multichannel=True meant."""

    def wrapped(image: Any, *args: Any, multichannel: bool | None = None, **kwargs: Any) -> Any:
        if multichannel and "channel_axis" not in kwargs:
            kwargs["channel_axis"] = -1
        return gaussian(image, *args, **kwargs)

    return wrapped


def library() -> Any:
    """The `imagecorruptions` module, its fixes applied once (see _pkg_resources_shim, _gaussian_compat; its import of
    scipy.ndimage.interpolation, deprecated in SciPy 1.x, warns once: silenced here). A missing install is one line."""
    if "module" in _LIB:
        return _LIB["module"]
    shimmed = False
    try:
        import pkg_resources  # noqa: F401
    except ImportError:  # the stand-in only while the library imports (it binds resource_filename then): left in
        sys.modules["pkg_resources"] = _pkg_resources_shim()  # sys.modules it would break pytest and setuptools
        shimmed = True
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            module = importlib.import_module(LIBRARY)
    except ImportError as exc:
        raise PairedGTAError(f"corruption conditions need the package {LIBRARY} ({exc}); install it with "
                             "pip install -e \".[corruptions]\" -c constraints.txt, or choose conditions without "
                             "corruptions") from None
    finally:
        if shimmed:
            sys.modules.pop("pkg_resources", None)
    inner = sys.modules[f"{LIBRARY}.corruptions"]
    if not getattr(inner.gaussian, "_pairedgta_compat", False):
        inner.gaussian = _gaussian_compat(inner.gaussian)
        inner.gaussian._pairedgta_compat = True
    _LIB["module"] = module
    return module


def installed() -> bool:
    return importlib.util.find_spec(LIBRARY) is not None


def library_version() -> str:
    """The installed library's version: part of a corrupted dataset's cache key (another version, other pixels)."""
    try:
        return importlib.metadata.version(LIBRARY)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def seed_for(base_seed: int, scene: str, condition: str) -> int:
    """A 32-bit seed from (run seed, scene id, condition name) only: the same scene and config give the same image,
    whatever the worker, shard or order."""
    words = [int(base_seed) & 0xFFFFFFFF, zlib.crc32(str(scene).encode()), zlib.crc32(str(condition).encode())]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


@contextlib.contextmanager
def global_seed(seed: int) -> Iterator[None]:
    """numpy's global generator seeded inside, its previous state restored after: the library draws from it
    (noise, glass blur, motion-blur angle, snow, frost's crop, fog's fractal, spatter, elastic transform)."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def corrupt(image: np.ndarray, corruption: str, severity: int, seed: int) -> np.ndarray:
    """`image` (H x W x 3 uint8, at least 32 x 32) under one corruption at one severity, seeded: byte-identical for the
    same inputs: the library's own output, its size checked."""
    if corruption not in SUBSETS["all"] or int(severity) not in SEVERITIES:
        raise ConfigError(f"corruption {corruption!r} at severity {severity!r}; use one of {', '.join(SUBSETS['all'])} "
                          "at 1..5")
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise PairedGTAError(f"corruption {corruption}: expected an H x W x 3 uint8 image, got {image.dtype} "
                             f"{image.shape}")
    if min(image.shape[:2]) < 32:
        raise ConfigError(f"corruption {corruption}: the image is {image.shape[1]}x{image.shape[0]}, the library needs "
                          "at least 32x32; set renderer.width and renderer.height >= 32")
    lib = library()
    with global_seed(seed), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = lib.corrupt(np.ascontiguousarray(image), corruption_name=corruption, severity=int(severity))
    out = np.asarray(out, dtype=np.uint8)
    if out.shape != image.shape:
        raise PairedGTAError(f"corruption {corruption}: the library returned {out.shape} for {image.shape}")
    return out


def hash_config(grid: Any) -> dict[str, Any]:
    """What of the corruptions decides a dataset's pixels beyond the conditions themselves: the library and its
    version. Empty for a set without corruption conditions, so rendered sets hash as before."""
    if not any(getattr(c, "corruption", None) for c in grid):
        return {}
    return {"corruptions": {"library": LIBRARY, "version": library_version()}}


__all__ = ["COMMON", "PREFIX", "SEVERITIES", "SLOW", "SUBSETS", "VALIDATION", "condition_name", "conditions", "corrupt",
           "global_seed", "hash_config", "installed", "library", "library_version", "options", "parse_name",
           "seed_for"]
