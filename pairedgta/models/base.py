"""The one interface every model family implements.

Callers always pass RGB in [0, 1]; normalisation, resizing and padding belong to the model and are
applied inside `predict_proba`, so a wrong preprocessing cannot leak in from a caller.
"""
from __future__ import annotations

import abc
import math
from typing import Sequence

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import DataError, ModelError

from pairedgta.lazy import lazy_module
from pairedgta.models.runtime import RuntimeOptions

torch = lazy_module("torch")  # imported on first use: a cached run needs none
F = lazy_module("torch.nn.functional")


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class Segmenter(abc.ABC):
    """A Cityscapes segmenter: B x 3 x H x W RGB in [0,1] -> B x 19 x H x W probabilities at input size."""

    num_classes: int = NUM_CLASSES
    class_names: Sequence[str] = CLASS_NAMES

    def __init__(self, name: str, module: torch.nn.Module, runtime: RuntimeOptions | None = None) -> None:
        runtime = runtime or RuntimeOptions()
        self.name = name
        self.device = resolve_device(runtime.device)
        self.batch_size = runtime.batch_size
        self.amp = runtime.amp if self.device.type == "cuda" else None
        module = module.eval().to(self.device)
        self.channels_last = runtime.channels_last and self.device.type == "cuda"
        if self.channels_last:
            module = module.to(memory_format=torch.channels_last)
        self.module = torch.compile(module) if runtime.compile else module

    # -- to implement -------------------------------------------------------------------------
    @abc.abstractmethod
    def _logits(self, images: torch.Tensor) -> torch.Tensor:
        """Normalised probabilities or logits source: return B x C x h x w *logits* for [0,1] input.
        Families whose output is already a distribution override `_probabilities` instead."""

    def _probabilities(self, images: torch.Tensor) -> torch.Tensor:
        logits = self._logits(images)
        logits = F.interpolate(logits.float(), size=images.shape[-2:], mode="bilinear", align_corners=False)
        return logits.softmax(dim=1)

    # -- public API ----------------------------------------------------------------------------
    def _as_tensor(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        if isinstance(images, np.ndarray):
            # astype copies, so read-only arrays (decoded images) are fine
            if images.dtype == np.uint8:
                images = torch.from_numpy(images.astype(np.float32)).div_(255.0)
            else:
                images = torch.from_numpy(images.astype(np.float32))
            if images.ndim == 3:
                images = images.unsqueeze(0)
            if images.shape[-1] == 3 and images.shape[1] != 3:
                images = images.permute(0, 3, 1, 2)
        if images.ndim == 3:
            images = images.unsqueeze(0)
        if images.ndim != 4 or images.shape[1] != 3:
            raise DataError(
                f"{self.name}: expected images of shape B x 3 x H x W (RGB in [0,1]), got {tuple(images.shape)}"
            )
        return images.float()

    def predict_proba(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """B x 3 x H x W RGB in [0,1] -> B x num_classes x H x W probabilities (on the CPU)."""
        with torch.inference_mode():
            return self._predict_proba(images)

    def _predict_proba(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        images = self._as_tensor(images)
        outputs = []
        for start in range(0, images.shape[0], self.batch_size):
            chunk = images[start : start + self.batch_size].to(self.device, non_blocking=True)
            if self.channels_last:
                chunk = chunk.contiguous(memory_format=torch.channels_last)
            try:
                if self.amp:
                    dtype = torch.bfloat16 if self.amp == "bf16" else torch.float16
                    with torch.autocast(device_type="cuda", dtype=dtype):
                        probs = self._probabilities(chunk)
                else:
                    probs = self._probabilities(chunk)
            except RuntimeError as exc:
                if "out of memory" in str(exc).lower():
                    raise ModelError(f"{self.name}: out of memory on {self.device}; lower model.batch_size") from None
                first = str(exc).strip().splitlines()[0][:200]
                raise ModelError(
                    f"{self.name}: forward failed on a {chunk.shape[-1]}x{chunk.shape[-2]} image ({first}); "
                    "check the image size the model accepts"
                ) from None
            if not bool(torch.isfinite(probs).all()):  # NaN weights would score xi 0 everywhere, silently
                raise ModelError(f"{self.name}: the model's outputs are not finite (NaN or inf); its weights are "
                                 "broken: re-export or download them again")
            outputs.append(probs.float().cpu())
        return torch.cat(outputs, dim=0)

    def predict(self, images: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (labels B x H x W int64, confidence B x H x W float: the max probability)."""
        probs = self.predict_proba(images)
        confidence, labels = probs.max(dim=1)
        return labels, confidence

    def predict_with_entropy(self, images: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """-> (labels, confidence, normalised entropy H(p) / log K in [0, 1]), all B x H x W, from one
        forward pass: the label-free estimators need the whole distribution, not only its maximum."""
        probs = self.predict_proba(images)
        confidence, labels = probs.max(dim=1)
        return labels, confidence, normalised_entropy(probs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, device={self.device})"


def normalised_entropy(probs: torch.Tensor) -> torch.Tensor:
    """B x K x H x W scores -> B x H x W entropy of the renormalised distribution over log K (0: certain,
    1: uniform). Families whose class scores do not sum to one (Mask2Former) are renormalised first."""
    p = probs.float().clamp_min(0)
    p = p / p.sum(dim=1, keepdim=True).clamp_min(1e-12)
    h = -(p * torch.log(p.clamp_min(1e-12))).sum(dim=1)
    return (h / math.log(p.shape[1])).clamp(0.0, 1.0)
