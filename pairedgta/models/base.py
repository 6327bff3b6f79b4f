"""The one interface every model family implements.

Callers always pass RGB in [0, 1]; normalisation, resizing and padding belong to the model and are
applied inside `predict_proba`, so a wrong preprocessing cannot leak in from a caller.
"""
from __future__ import annotations

import abc
import math
from typing import Any, Iterator, NamedTuple, Protocol, Sequence, Union

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import DataError, ModelError, PairedGTAError

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
        self._nonfinite: torch.Tensor | None = None  # device flag: some output since the last check was not finite

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
    def to_device(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """RGB images (B x H x W x 3 or B x 3 x H x W; uint8 0-255 or float 0-1; numpy or torch, on any device)
        -> float B x 3 x H x W in [0, 1] on this model's device. uint8 crosses to the device as uint8 (a quarter
        of the bytes; pinned and non-blocking on a GPU) and is converted there, by the same float32 division
        and into the same memory layout as the former host path, so the forward sees bit-identical input."""
        if isinstance(images, np.ndarray):
            if not (images.flags.writeable and images.flags.c_contiguous):  # decoded images are read-only
                images = np.array(images, copy=True, order="C")
            images = torch.from_numpy(images)
        if images.ndim == 3:
            images = images.unsqueeze(0)
        nhwc = images.ndim == 4 and images.shape[-1] == 3 and images.shape[1] != 3
        if not nhwc and (images.ndim != 4 or images.shape[1] != 3):
            raise DataError(
                f"{self.name}: expected images of shape B x 3 x H x W (RGB in [0,1]), got {tuple(images.shape)}"
            )
        images = to_device(images, self.device)
        if nhwc:
            images = images.permute(0, 3, 1, 2)  # a view: the NHWC memory layout the host path handed on
        if images.dtype == torch.uint8:
            return images.float().div_(255.0)
        return images.float()

    def _scores(self, images: torch.Tensor, energy: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(probabilities, with `energy` the per-pixel logsumexp of the logits they are the softmax of): one forward
        for both. None where the family's output is already a distribution, not a softmax of `_logits` (Mask2Former)."""
        if energy and type(self)._probabilities.__qualname__ in SOFTMAX_OF_LOGITS:
            logits = self._logits(images)
            if type(self)._probabilities is Segmenter._probabilities:  # at the model's resolution: as `_probabilities`
                logits = F.interpolate(logits.float(), size=images.shape[-2:], mode="bilinear", align_corners=False)
            return logits.softmax(dim=1), logsumexp_classes(logits.float())
        return self._probabilities(images), None

    def _forward(self, chunk: torch.Tensor, energy: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor | None]:
        """One chunk (<= batch_size images, on the device) -> its probabilities on the device (float32); with
        `energy`, (probabilities, per-pixel logsumexp of the logits or None: `_scores`)."""
        if self.channels_last:
            chunk = chunk.contiguous(memory_format=torch.channels_last)
        try:
            if self.amp:
                dtype = torch.bfloat16 if self.amp == "bf16" else torch.float16
                with torch.autocast(device_type=self.device.type, dtype=dtype):
                    probs, lse = self._scores(chunk, energy)
            else:
                probs, lse = self._scores(chunk, energy)
        except PairedGTAError:  # a RuntimeError too, but one that names its cause (e.g. outputs vs label space)
            raise
        except RuntimeError as exc:
            if "out of memory" in str(exc).lower():
                raise ModelError(f"{self.name}: out of memory on {self.device}; lower model.batch_size") from None
            first = str(exc).strip().splitlines()[0][:200]
            raise ModelError(
                f"{self.name}: forward failed on a {chunk.shape[-1]}x{chunk.shape[-2]} image ({first}); "
                "check the image size the model accepts"
            ) from None
        return (probs.float(), lse) if energy else probs.float()

    def _chunks(self, images: np.ndarray | torch.Tensor) -> Iterator[torch.Tensor]:
        x = self.to_device(images)
        for start in range(0, x.shape[0], self.batch_size):
            yield self._forward(x[start : start + self.batch_size])

    def probabilities(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """B x num_classes x H x W probabilities on the model's device; no host synchronisation, no check
        (`predict_proba` checks and copies to the CPU; `predict_maps` reduces on the device)."""
        with torch.inference_mode():
            return _cat(list(self._chunks(images)))

    def predict_maps(self, images: np.ndarray | torch.Tensor, entropy: bool = True, energy: bool = False,
                     gram: bool = False) -> PixelMaps:
        """The per-pixel maps every stage derives from the probabilities, on the device, chunk by chunk (a
        chunk's probabilities are freed before the next forward): labels (uint8), max probability and, with
        `entropy`, the normalised entropy; with `energy` the logsumexp of the logits (None without logits), with
        `gram` each image's Gram matrix of its softmax matrix (`gram_matrices`). Nothing crosses to the host;
        whether every output was finite is kept as a device flag that `check_finite` reads once, at the end of a
        stage."""
        labels, confidence, entropies, energies, grams = [], [], [], [], []
        x = self.to_device(images)
        with torch.inference_mode():
            for start in range(0, x.shape[0], self.batch_size):
                chunk = x[start : start + self.batch_size]
                probs, lse = self._forward(chunk, energy=True) if energy else (self._forward(chunk), None)
                conf, lab = max_and_label(probs)
                self._note_finite(conf)
                labels.append(lab)
                confidence.append(conf)
                energies.append(lse)
                if gram:
                    grams.append(gram_matrices(probs))
                if entropy:
                    entropies.append(normalised_entropy_(probs))  # probs is ours and not needed after this
                del probs
            lse_all = _cat(energies) if energy and all(e is not None for e in energies) else None
            return PixelMaps(_cat(labels), _cat(confidence), _cat(entropies) if entropy else None, lse_all,
                             _cat(grams) if gram else None)

    def _note_finite(self, confidence: torch.Tensor) -> None:
        """Accumulates "all outputs finite" on the device. NaN or +inf anywhere in a pixel's distribution is
        its maximum (torch.max propagates NaN), so the B x H x W maximum decides for the whole distribution."""
        bad = ~torch.isfinite(confidence).all()
        self._nonfinite = bad if self._nonfinite is None else self._nonfinite | bad

    def check_finite(self) -> None:
        """Raises ModelError if any output since the last check was not finite; the one host synchronisation a
        stage pays for it (NaN weights would score xi 0 everywhere, silently)."""
        flag, self._nonfinite = self._nonfinite, None
        if flag is not None and bool(flag):
            raise ModelError(f"{self.name}: the model's outputs are not finite (NaN or inf); its weights are "
                             "broken: re-export or download them again")

    def predict_proba(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """B x 3 x H x W RGB in [0,1] -> B x num_classes x H x W probabilities (on the CPU). The full tensor
        crosses to the host: for callers that need the distribution itself, not for the stages."""
        probs = self.probabilities(images)
        if not bool(torch.isfinite(probs).all()):
            self._nonfinite = torch.ones((), dtype=torch.bool)
        self.check_finite()
        return probs.cpu()

    def predict(self, images: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (labels B x H x W int64, confidence B x H x W float: the max probability), on the CPU; only these
        two maps cross to the host."""
        maps = self.predict_maps(images, entropy=False)
        self.check_finite()
        return maps.labels.long().cpu(), maps.confidence.cpu()

    def predict_with_entropy(self, images: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """-> (labels, confidence, normalised entropy H(p) / log K in [0, 1]), all B x H x W on the CPU, from one
        forward pass: the label-free estimators need the whole distribution, not only its maximum."""
        maps = self.predict_maps(images, entropy=True)
        self.check_finite()
        return maps.labels.long().cpu(), maps.confidence.cpu(), maps.entropy.cpu()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, device={self.device})"


class BoxModel(Protocol):
    """What a detector gives the stages (pairedgta/models/detectors.py Detector, contract.ContractDetector): its boxes
    per image of an RGB uint8 batch, at or above its operating threshold counted as found."""

    name: str
    device: Any
    score_threshold: float

    def detect(self, images: np.ndarray) -> list[Any]:
        ...


Model = Union[Segmenter, BoxModel]  # what the one builder (pairedgta.models.build_model) returns, by model kind


class PixelMaps(NamedTuple):
    """What the stages keep of a batch's probabilities, on the model's device: B x H x W each."""

    labels: torch.Tensor                 # argmax class, uint8 (int64 for more than 256 classes)
    confidence: torch.Tensor             # max probability, float32
    entropy: torch.Tensor | None = None  # normalised entropy in [0, 1], float32
    energy: torch.Tensor | None = None   # logsumexp of the logits (negative energy), float32; None without logits
    gram: torch.Tensor | None = None     # B x K x K: P^T P of each image's softmax matrix P (pixels x K), float64


def to_device(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A host tensor onto `device`: on a GPU from pinned memory and non-blocking (pageable memory would make the
    copy wait for the GPU's queue); unchanged when it is there already."""
    if tensor.device == device:
        return tensor
    if device.type == "cuda" and tensor.device.type == "cpu" and not tensor.is_pinned():
        tensor = tensor.pin_memory()
    return tensor.to(device, non_blocking=True)


def max_and_label(probs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`probs.max(dim=1)` as (values, uint8 indices), the first maximal class on ties as torch.max returns it.
    On the CPU max-with-indices over the class axis is a scalar loop (7x amax's time here), so there the maximum
    comes from `amax` and the class as the highest of the weights K - k where p_k equals it: vector passes, the
    same numbers (a pixel whose maximum is NaN gets label K, no class; check_finite reports it)."""
    k = probs.shape[1]
    if k > 255 or probs.device.type != "cpu":  # a GPU's max-with-indices is one pass, with the same tie rule
        conf, labels = probs.max(dim=1)
        return conf, labels.to(torch.uint8) if k <= 255 else labels
    conf = probs.amax(dim=1, keepdim=True)
    weights = torch.arange(k, 0, -1, dtype=torch.uint8, device=probs.device).view(1, k, *([1] * (probs.ndim - 2)))
    first = ((probs == conf) * weights).amax(dim=1)
    return conf.squeeze(1), k - first


# the families' `_probabilities` that are the softmax of their `_logits` (at input size after `Segmenter`'s upsampling)
SOFTMAX_OF_LOGITS = ("Segmenter._probabilities", "NormalizedSegmenter._probabilities")


# exp of a difference below this is subnormal in float32 (exp(-87) = 1.6e-38 is the last normal one)
SUBNORMAL_EXP = -87.0


def logsumexp_classes(logits: torch.Tensor) -> torch.Tensor:
    """B x K x H x W -> B x H x W logsumexp over the classes, by torch.logsumexp's own steps (the maximum, with an
    infinite one taken as 0; exp of the differences, their sum, its log, plus the maximum), but with the
    differences below SUBNORMAL_EXP raised to it before exp: on the CPU exp of a subnormal result is ~12x slower,
    and a peaked model's logits make most of them (10 of a SegFormer-B0 forward's 38 ms an image at 512x256).
    Every pixel's sum holds exp(0) = 1, beside which such a term is far below half an ulp: the same floats as
    torch.logsumexp (tests/test_logsumexp.py)."""
    maxes = logits.amax(dim=1, keepdim=True)
    shift = maxes.squeeze(1)  # a view: filled in place, as torch fills its maxes
    empty = shift == -math.inf  # every logit -inf: torch's sum is 0 and its log -inf, which the raised terms are not
    shift.masked_fill_(shift.abs() == math.inf, 0)
    out = (logits - maxes).clamp_min_(SUBNORMAL_EXP).exp_().sum(dim=1).log_().add_(shift)
    return out.masked_fill_(empty, -math.inf)


def gram_matrices(probs: torch.Tensor) -> torch.Tensor:
    """B x K x H x W probabilities -> B x K x K: P^T P of each image's pixels x K matrix P (one float32 matmul on the
    device, handed on as float64). Grams of images add up to the Gram of their stacked pixels, whose eigenvalues
    are the squared singular values of P."""
    p = probs.flatten(2)
    return torch.bmm(p, p.transpose(1, 2)).double()


def _cat(parts: list[torch.Tensor]) -> torch.Tensor:
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=0)


def normalised_entropy(probs: torch.Tensor) -> torch.Tensor:
    """B x K x H x W scores -> B x H x W entropy of the renormalised distribution over log K (0: certain,
    1: uniform). Families whose class scores do not sum to one (Mask2Former) are renormalised first."""
    p = probs.float().clamp_min(0)
    p = p / p.sum(dim=1, keepdim=True).clamp_min(1e-12)
    h = -(p * torch.log(p.clamp_min(1e-12))).sum(dim=1)
    return (h / math.log(p.shape[1])).clamp(0.0, 1.0)


def normalised_entropy_(probs: torch.Tensor) -> torch.Tensor:
    """`normalised_entropy`, computed in place in `probs` (float32, which it overwrites): the same operations in
    the same order, so the same bits, with one temporary instead of five."""
    p = probs.clamp_min_(0)
    p.div_(p.sum(dim=1, keepdim=True).clamp_min_(1e-12))
    h = p.clamp_min(1e-12).log_().mul_(p).sum(dim=1).neg_()
    return h.div_(math.log(p.shape[1])).clamp_(0.0, 1.0)
