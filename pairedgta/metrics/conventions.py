"""The metric convention of a run (pairedgta/conf/metric/<name>.yaml): how absent classes score, which classes
the class-wise mean covers, how pixel agreement aggregates over images and which rho_valid selection is
the headline. Parsed and checked once here; the metric modules take the values as parameters, and every
output records the convention that made it."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ConfigError
from pairedgta.metrics.agreement import AGREEMENT_MODES
from pairedgta.metrics.ranking import SELECTIONS
from pairedgta.metrics.reference_consistency import ABSENT_POLICIES, mean_mask

CONVENTIONS = ("paper", "strict")  # the metric configs (metric=paper|strict); the name every output records


@dataclass(frozen=True)
class Convention:
    name: str                      # e.g. paper | strict: written into every output
    absent: str                    # xi of a class without reference pixels: nan | zero
    mean_exclude: tuple[str, ...]  # classes left out of the class-wise mean (and of Table 1)
    agreement: str                 # pooled | per_image
    rho_headline: str              # the rho_valid selection reported as the headline
    min_images: int = 0            # a class enters the mean only with reference pixels in >= min_images images
    min_pixels: int = 0            # ... and >= min_pixels reference pixels in all (0 and 0: every defined class)
    rho_min_frames: int = 0        # a rho_valid is a headline only over >= this many frames (metric.rho.min_frames)
    rpc_min_clean_miou: float = 0.0  # rPC is undefined below this clean GT mIoU (metric.validity.rpc_min_clean_miou)

    def supported(self, images, pixels):
        """Boolean mask over classes: enough support for the class-wise mean (images, pixels: per class)."""
        return support_mask(images, pixels, self.min_images, self.min_pixels)

    def mean_classes(self):
        """Boolean mask over the 19 Cityscapes classes: which enter the class-wise mean."""
        return mean_mask(len(CLASS_NAMES), CLASS_NAMES, self.mean_exclude)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["mean_exclude"] = list(self.mean_exclude)
        return d


def support_mask(images, pixels, min_images: int, min_pixels: int):
    """The strict convention's support rule, per class: reference pixels in >= min_images images and
    >= min_pixels in all. Without it a class seen in one image with 7 pixels weighs as much as road."""
    import numpy as np

    return (np.asarray(images) >= min_images) & (np.asarray(pixels) >= min_pixels)


def convention_from_config(metric: dict[str, Any], selections: list[str] | None = None) -> Convention:
    """metric: the `metric` config node; selections: the rho_valid selections the run computes."""
    name = str(metric.get("convention") or "strict")
    if name not in CONVENTIONS:
        raise ConfigError(f"metric.convention={name!r}; use one of {', '.join(CONVENTIONS)} (the metric configs: metric=paper "
                          "or metric=strict, whose keys can then be overridden one by one)")
    absent = str(metric.get("absent", "nan"))
    if absent not in ABSENT_POLICIES:
        raise ConfigError(f"metric.absent={absent!r}; use one of {', '.join(ABSENT_POLICIES)}")
    exclude = tuple(str(c) for c in (metric.get("mean_exclude") or ()))
    unknown = [c for c in exclude if c not in CLASS_NAMES]
    if unknown:
        raise ConfigError(f"metric.mean_exclude: unknown class(es) {unknown}; use Cityscapes names such as bus, train")
    agreement = str(metric.get("agreement", "pooled"))
    if agreement not in AGREEMENT_MODES:
        raise ConfigError(f"metric.agreement={agreement!r}; use one of {', '.join(AGREEMENT_MODES)}")
    rho = metric.get("rho") or {}
    selections = list(selections or rho.get("selections") or SELECTIONS)
    bad = [s for s in selections if s not in SELECTIONS]
    if bad:
        raise ConfigError(f"metric.rho.selections: unknown {bad}; use {list(SELECTIONS)}")
    headline = str(rho.get("headline") or selections[0])
    if headline not in selections:
        raise ConfigError(f"metric.rho.headline={headline!r} is not among metric.rho.selections={selections}")
    support = {}
    for key in ("min_images", "min_pixels"):
        value = metric.get(key, 0)
        if value is None:
            value = 0
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"metric.{key}={value!r} is invalid; set it to an integer >= 0 (0 = no support rule)")
        support[key] = value
    min_frames = rho.get("min_frames", 0)
    if min_frames is None:
        min_frames = 0
    if isinstance(min_frames, bool) or not isinstance(min_frames, int) or min_frames < 0:
        raise ConfigError(f"metric.rho.min_frames={min_frames!r} is invalid; set it to an integer >= 0 (0 = any number)")
    floor = (metric.get("validity") or {}).get("rpc_min_clean_miou", 0.0)
    if floor is None:
        floor = 0.0
    if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not 0.0 <= floor < 1.0:
        raise ConfigError(f"metric.validity.rpc_min_clean_miou={floor!r} is invalid; set a clean mIoU in [0, 1) (0 = no floor)")
    return Convention(name, absent, exclude, agreement, headline, **support, rho_min_frames=min_frames,
                      rpc_min_clean_miou=float(floor))
