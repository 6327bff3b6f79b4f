"""How a model runs, as opposed to what it is: the options every family shares, with one default each.

A model's config (pairedgta/conf/model/<name>.yaml, `model.<key>=` overrides) may set any of these; the family
builders never see them as keys: `build_model` parses them once into `RuntimeOptions` and hands that to the
family, which passes it to `Segmenter`. Torch-free, so a cached run can check and fill a config without torch.
"""
from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Iterator, Mapping

from pairedgta.errors import ConfigError

AMP_CHOICES = (None, "bf16", "fp16")
# the input normalisation of ImageNet-pretrained backbones: every family's default model.mean / model.std
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _speed_only(default: Any) -> Any:
    """An option that changes how fast a model runs, never its numbers: left out of the stage hashes."""
    return field(default=default, metadata={"speed_only": True})


@dataclass(frozen=True)
class RuntimeOptions:
    """`device` comes from the run's top-level `device`; the others from the model config. `amp` changes the
    numbers, so it enters the stage hashes; the options marked speed-only do not (SPEED_ONLY_KEYS)."""

    device: str = _speed_only("cpu")
    batch_size: int = _speed_only(4)
    amp: str | None = None
    channels_last: bool = _speed_only(False)
    compile: bool = _speed_only(False)

    def __post_init__(self) -> None:
        size = self.batch_size
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ConfigError(f"model.batch_size={size!r} must be a whole number >= 1, e.g. model.batch_size=4")
        if self.amp not in AMP_CHOICES:
            raise ConfigError(f"model.amp={self.amp!r} is not one of null, bf16, fp16; e.g. model.amp=bf16 (CUDA only)")
        for key in ("channels_last", "compile"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"model.{key}={getattr(self, key)!r} must be true or false")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], device: str | None = None) -> "RuntimeOptions":
        """The runtime options a model config sets (missing ones take the defaults above)."""
        given = {k: cfg[k] for k in MODEL_KEYS if k in cfg}
        return cls(device=str(device or "cpu"), **given)


# the options a model config may set (device is the run's, never a model's own key)
MODEL_KEYS = tuple(f.name for f in fields(RuntimeOptions) if f.name != "device")
# the keys a stage leaves out of its hash: two runs that differ only in these give the same numbers
SPEED_ONLY_KEYS = tuple(f.name for f in fields(RuntimeOptions) if f.metadata.get("speed_only"))


def split_runtime(cfg: Mapping[str, Any], device: str | None = None) -> tuple[dict[str, Any], RuntimeOptions]:
    """(the family's own keys, the parsed runtime options) of one model config."""
    family_keys = {k: v for k, v in cfg.items() if k not in MODEL_KEYS}
    return family_keys, RuntimeOptions.from_config(cfg, device)


def runtime_defaults() -> dict[str, Any]:
    """The default of every option a model config may set, as the config would spell it."""
    return {k: v for k, v in asdict(RuntimeOptions()).items() if k in MODEL_KEYS}


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Torch's CPU threads for a block of forwards (the run's `threads`: results depend on it), put back afterwards;
    None leaves them as they are."""
    if n is None:
        yield
        return
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


_REUSING: list[bool] = []


def reuse_freed_memory() -> bool:
    """Keep freed memory in the process for the next allocation instead of giving it back to the kernel.

    glibc maps every allocation above 32 MB afresh and unmaps it when freed. A batch's probabilities are such
    allocations (4 x 19 x 256 x 512 floats = 40 MB), and each forward makes several. Every new map is faulted in and
    zeroed page by page: on the 2-core machine that was half of a SegFormer-B0 forward at 512x256 (76 against
    38 ms an image; experiments/bench_evaluate.py). With mmap off (M_MMAP_MAX 0) and no trimming, freed blocks are
    reused. The numbers do not change; the process keeps its peak memory until it ends. glibc only (elsewhere
    nothing); once per process; True where it applies. PAIREDGTA_REUSE_FREED_MEMORY=0 in the environment keeps
    glibc's defaults (a process that must give memory back while it runs)."""
    if _REUSING:
        return _REUSING[0]
    import ctypes
    import os
    import platform

    ok = False
    wanted = os.environ.get("PAIREDGTA_REUSE_FREED_MEMORY", "1") != "0"
    if wanted and platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        try:
            libc = ctypes.CDLL(None)
            m_trim_threshold, m_mmap_max = -1, -4  # glibc's malloc.h
            ok = bool(libc.mallopt(m_mmap_max, 0)) and bool(libc.mallopt(m_trim_threshold, 2**31 - 1))
        except (OSError, AttributeError):
            ok = False
    _REUSING.append(ok)
    return ok


__all__ = ["torch_threads", "reuse_freed_memory", "RuntimeOptions", "IMAGENET_MEAN", "IMAGENET_STD", "MODEL_KEYS",
           "split_runtime", "runtime_defaults"]
