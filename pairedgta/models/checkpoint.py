"""Strict checkpoint loading and the shared wrapper for the in-project architectures.

Released checkpoints come in several layouts (bare state dict, nested under `state_dict` / `model_state` /
`model`, keys prefixed by `module.` (DataParallel) or `model.` (training wrappers)). All of them are accepted,
but after the documented normalisation every remaining key must match the architecture exactly: a silently
skipped block would still produce plausible-looking but wrong predictions.
"""
from __future__ import annotations

import inspect
import logging
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from pairedgta.errors import ModelError, reason
from pairedgta.models.base import Segmenter
from pairedgta.models.hf_common import check_zoo_path, resolve_checkpoint_path
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD, RuntimeOptions

log = logging.getLogger(__name__)

NESTING_KEYS = ("state_dict", "model_state", "model")
STRIP_PREFIXES = ("module.", "model.")
# Loss buffers saved by training wrappers (e.g. the class weights of a weighted cross-entropy).
LOSS_PREFIXES = ("loss.", "sem_loss.", "bd_loss.")
_SHOW = 4  # keys listed per category in an error message


def _numpy_safe_globals() -> list[Any]:
    """Numpy scalars/dtypes are plain numbers (e.g. a stored `best_score`); allowing them is harmless."""
    allowed: list[Any] = [np.dtype]
    if int(np.__version__.split(".")[0]) >= 2:
        from numpy._core.multiarray import scalar

        allowed += [scalar, (scalar, "numpy.core.multiarray.scalar")]  # also numpy-1 pickles
    else:
        from numpy.core.multiarray import scalar

        allowed.append(scalar)
    for t in (np.float16, np.float32, np.float64, np.int32, np.int64, np.bool_):
        allowed.append(type(np.dtype(t)))
    return allowed


def _first_line(exc: BaseException) -> str:
    """The whole reason on one line (a refused pickle names the global, e.g. posix.system)."""
    return reason(exc)


def _is_state_dict(obj: Any) -> bool:
    return isinstance(obj, Mapping) and len(obj) > 0 and all(isinstance(v, torch.Tensor) for v in obj.values())


# A whole model in a checkpoint's place, by its bytes (pairedgta/models/sources/files.py: identify): the source that
# loads it. torch.load would fail on it with its own internal error (a .pt2 zip has no data.pkl).
PROGRAMS = {"pt2": ("a torch.export program", "model=export model.path={file}"),
            "onnx": ("an ONNX model", "model=onnx model.path={file}")}


def not_weights(path: Path, model_name: str) -> None:
    """A torch.export program or an ONNX graph given as model.checkpoint_path: the one line naming the source that
    loads it (checked before torch.load; only the first bytes and a zip's entry names are read)."""
    from pairedgta.models.sources.files import identify

    try:
        kind = identify(path)
    except OSError:
        return  # unreadable: torch.load says why
    if kind in PROGRAMS:
        what, use = PROGRAMS[kind]
        raise ModelError(f"{model_name}: model.checkpoint_path={path} is {what}: use {use.format(file=path)}")


def read_state_dict(path: str | Path, *, model_name: str = "model") -> dict[str, torch.Tensor]:
    """Read a checkpoint file into a flat state dict with the documented nesting and prefixes removed."""
    check_zoo_path(path, model_name)
    path = resolve_checkpoint_path(path)
    if not path.is_file():
        raise ModelError(f"{model_name}: checkpoint file {path} does not exist; fix model.checkpoint_path=")
    not_weights(path, model_name)
    try:
        if path.suffix == ".safetensors":  # the zoo's own weights: a flat tensor file, no pickle at all
            from safetensors.torch import load_file

            # the zoo stores weights in half precision to stay small; the model computes in float32
            obj = {k: v.float() if v.is_floating_point() else v for k, v in load_file(str(path), device="cpu").items()}
        else:
            with torch.serialization.safe_globals(_numpy_safe_globals()):
                obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt, truncated, or not a weights-only torch / safetensors file
        raise ModelError(
            f"{model_name}: cannot read checkpoint {path} ({_first_line(exc)}); expected a torch state-dict "
            "or safetensors file"
        ) from None
    seen = 0
    while not _is_state_dict(obj):
        nested = next((k for k in NESTING_KEYS if isinstance(obj, Mapping) and isinstance(obj.get(k), Mapping)), None)
        if nested is None or seen > 3:
            found = ", ".join(map(str, list(obj)[:8])) if isinstance(obj, Mapping) else type(obj).__name__
            raise ModelError(
                f"{model_name}: checkpoint {path} holds no state dict (found: {found}); expected tensors at the top "
                f"level or under one of {', '.join(NESTING_KEYS)}"
            )
        obj = obj[nested]
        seen += 1
    state: dict[str, torch.Tensor] = {}
    for key, value in obj.items():
        name = str(key)
        while name.startswith(STRIP_PREFIXES):
            name = name.split(".", 1)[1]
        if name in state:
            raise ModelError(f"{model_name}: checkpoint {path} has '{key}' twice after removing module./model. prefixes")
        state[name] = value
    return state


def _listing(keys: Sequence[str]) -> str:
    shown = ", ".join(keys[:_SHOW])
    return f"{shown}, ..." if len(keys) > _SHOW else shown


def load_checkpoint_strict(
    module: torch.nn.Module,
    path: str | Path,
    *,
    training_only_prefixes: Iterable[str] = (),
    model_name: str = "model",
) -> list[str]:
    """Load `path` into `module` with every key accounted for; returns the training-only keys that were dropped.

    Keys under `training_only_prefixes` (auxiliary heads, loss buffers) are reported in one log line and dropped;
    any other missing, unexpected or shape-mismatched key raises ModelError.
    """
    state = read_state_dict(path, model_name=model_name)  # resolves a pkg:// path itself (and names a missing zoo)
    expected = module.state_dict()
    prefixes = tuple(training_only_prefixes) + LOSS_PREFIXES

    extra = [k for k in state if k not in expected]
    dropped = sorted(k for k in extra if k.startswith(prefixes))
    unexpected = sorted(k for k in extra if not k.startswith(prefixes))
    missing = sorted(k for k in expected if k not in state)
    mismatched = sorted(k for k in expected if k in state and tuple(state[k].shape) != tuple(expected[k].shape))
    if missing or unexpected or mismatched:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing ({_listing(missing)})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected ({_listing(unexpected)})")
        if mismatched:
            shapes = [f"{k} file {list(state[k].shape)} vs model {list(expected[k].shape)}" for k in mismatched]
            parts.append(f"{len(mismatched)} shape mismatches ({_listing(shapes)})")
        raise ModelError(
            f"{model_name}: checkpoint {path} does not fit the architecture: {'; '.join(parts)}; "
            f"is model.checkpoint_path the released file for {model_name}?"
        )
    if dropped:
        heads = sorted({k.split(".", 1)[0] for k in dropped})
        log.info("%s: dropped %d training-only entries (%s) from %s", model_name, len(dropped), ", ".join(heads), path)
    module.load_state_dict({k: v for k, v in state.items() if k in expected}, strict=True)
    return dropped


# ---------------------------------------------------------------------------------------------------------------
# The shared builder of the in-project families (deeplabv3plus / pidnet / ddrnet): normalisation, padding, weights.


class NormalizedSegmenter(Segmenter):
    """Normalises, pads to `pad_multiple` (bottom/right, zeros after normalisation), runs, upsamples and crops.

    `_logits` already returns logits at input size, because cropping the padding is only exact at full size.
    """

    def __init__(
        self,
        name: str,
        module: torch.nn.Module,
        *,
        mean: Sequence[float],
        std: Sequence[float],
        pad_multiple: int = 1,
        align_corners: bool = False,
        runtime: RuntimeOptions | None = None,
    ) -> None:
        super().__init__(name, module, runtime)
        self.pad_multiple = max(1, int(pad_multiple))
        self.align_corners = bool(align_corners)
        self.mean = torch.tensor(mean, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(std, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    def _logits(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[-2:]
        x = (images.float() - self.mean) / self.std
        pad_h = -height % self.pad_multiple
        pad_w = -width % self.pad_multiple
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h))
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        logits = self.module(x)
        logits = F.interpolate(
            logits.float(), size=(height + pad_h, width + pad_w), mode="bilinear", align_corners=self.align_corners
        )
        return logits[..., :height, :width]

    def _probabilities(self, images: torch.Tensor) -> torch.Tensor:
        return self._logits(images).softmax(dim=1)


def build_network(architecture: Callable[..., torch.nn.Module], cfg: Mapping[str, Any], *,
                  augment: bool = False) -> torch.nn.Module:
    """The network a model config describes: a family's `architecture(name, augment, *, <its keys>)` called with
    the keys `cfg` sets (a missing one takes the architecture's default; any other key, e.g. an input option, is
    not the architecture's). `augment=True` adds the training-only heads (experiments/train_demo_model.py)."""
    keys = [p.name for p in inspect.signature(architecture).parameters.values() if p.kind is p.KEYWORD_ONLY]
    return architecture(cfg.get("name"), augment, **{k: cfg[k] for k in keys if k in cfg})


def build_inproject(
    architecture: Callable[..., torch.nn.Module], /, *, name: str, family: str, checkpoint_path: str | None = None,
    checkpoint_file: str | None = None, checkpoint_source: str | None = None, random_init: bool = False,
    init_seed: int | None = None, mean: list = IMAGENET_MEAN, std: list = IMAGENET_STD, pad_multiple: int = 1,
    upsample_align_corners: bool = False, runtime: RuntimeOptions, **arch: Any,
) -> NormalizedSegmenter:
    """The one builder of the in-project families (timm's build_model_with_cfg; each family is registered `via`
    it in pairedgta/models/__init__.py). Its keyword arguments are the input options every such family has, with
    their one default (a family's module may set its own in `PRETRAINED`, e.g. pidnet's upsample_align_corners);
    `arch` are the keyword-only arguments of the family's `architecture`, defaults filled in by the registry
    (pairedgta/registry.py), checked by pairedgta/models/__init__.py: check_model_config. From the family's module
    it reads its released weights (CHECKPOINT_FILE, CHECKPOINT_SOURCE) and TRAINING_ONLY_PREFIXES.
    Seeds, constructs, loads the weights strictly, wraps."""
    name = str(name or family)
    family_module = inspect.getmodule(architecture)
    if not checkpoint_path and not random_init:
        file = checkpoint_file or family_module.CHECKPOINT_FILE
        source = checkpoint_source or family_module.CHECKPOINT_SOURCE
        raise ModelError(
            f"model '{name}' needs its released weights ({file}; published at {source}); "
            f"download them and set model.checkpoint_path=<path to the file>"
        )
    with torch.random.fork_rng(devices=[]):
        if init_seed is not None:
            torch.manual_seed(int(init_seed))
        module = architecture(name, False, **arch)
    if checkpoint_path:
        load_checkpoint_strict(module, checkpoint_path, training_only_prefixes=family_module.TRAINING_ONLY_PREFIXES,
                               model_name=name)
    return NormalizedSegmenter(name, module, mean=[float(v) for v in mean], std=[float(v) for v in std],
                               pad_multiple=pad_multiple, align_corners=upsample_align_corners, runtime=runtime)


__all__ = ["load_checkpoint_strict", "read_state_dict", "NormalizedSegmenter", "build_network", "build_inproject"]
