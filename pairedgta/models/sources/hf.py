"""`model=hf`: any transformers checkpoint that AutoModelForSemanticSegmentation or AutoModelForUniversalSegmentation
loads, from a save_pretrained folder (`model.path`, offline) or the hub (`model.hub_id`, `model.revision`).

What loading runs: transformers' own classes for the config's model_type, never remote code (trust_remote_code is
off); the weights are data (safetensors, else transformers' torch.load(weights_only=True)) and must hold every
weight of the model: a head that from_pretrained would initialise at random (a classification checkpoint loaded for
segmentation) is an error, not a silently random model. A semantic model returns its logits; a universal one
(Mask2Former, MaskFormer, OneFormer) returns the class distribution of its queries, computed as the mask2former
family does (hf_common.query_class_scores). The folder's image processor declares the input (mean/std, resize, pad
multiple, channel order: `processor_contract`); the config's id2label names the channels for the label map."""
from __future__ import annotations

import contextlib
import inspect
import logging
from pathlib import Path
from typing import Any, Iterator

from pairedgta.errors import ModelError, reason
from pairedgta.models.contract import Network
from pairedgta.models.hf_common import guarded_pretrained, pretrained_source

log = logging.getLogger("pairedgta.models")

# OneFormer conditions its queries on a task; the semantic one is what the metrics compare
ONEFORMER_TASK = "the task is semantic"


def _kind(config: Any, where: str, shown: str) -> str:
    """'semantic' or 'universal': which Auto class loads the config's model_type."""
    from transformers.models.auto.modeling_auto import (MODEL_FOR_SEMANTIC_SEGMENTATION_MAPPING_NAMES,
                                                        MODEL_FOR_UNIVERSAL_SEGMENTATION_MAPPING_NAMES)

    model_type = getattr(config, "model_type", None)
    if model_type in MODEL_FOR_UNIVERSAL_SEGMENTATION_MAPPING_NAMES:
        return "universal"
    if model_type in MODEL_FOR_SEMANTIC_SEGMENTATION_MAPPING_NAMES:
        return "semantic"
    archs = ", ".join(getattr(config, "architectures", None) or []) or "no architectures"
    raise ModelError(
        f"{where}: {shown} is a '{model_type}' model ({archs}), which neither AutoModelForSemanticSegmentation nor "
        f"AutoModelForUniversalSegmentation loads; give a segmentation checkpoint (semantic: "
        f"{', '.join(MODEL_FOR_SEMANTIC_SEGMENTATION_MAPPING_NAMES)}; universal: "
        f"{', '.join(MODEL_FOR_UNIVERSAL_SEGMENTATION_MAPPING_NAMES)})")


def processor_contract(proc: Any, where: str = "model") -> dict[str, Any]:
    """The contract keys an image processor implies, for RGB input in [0, 1].

    The processor maps 0-255 pixels p to ((p * f) - mean) / std (f: rescale_factor when do_rescale, else 1; mean 0 and
    std 1 without do_normalize). With x = p / 255 that is (x * 255f - mean) / std: 255f = 1 (f = 1/255) is scale 1 with
    the processor's mean/std; no rescaling (f = 1) is scale 255 with them; any other factor is scale 1 with mean and std
    divided by 255f. A processor that does not normalise declares mean 0, std 1 (the contract's default is ImageNet's).
    Resizing (only with do_resize): {height, width} -> [h, w]; {shortest_edge} -> the short side (a longest_edge cap
    is not applied: logged); a size the contract cannot say is logged and left to model.resize. The processor's
    padding multiple (size_divisor / size_divisibility) is pad_multiple (the contract pads bottom and right, as
    Mask2Former's processor does); do_flip_channel_order is BGR input; a center crop is not applied (the whole image
    is segmented)."""
    out: dict[str, Any] = {}
    factor = float(getattr(proc, "rescale_factor", 1 / 255) or 1 / 255) if getattr(proc, "do_rescale", True) else 1.0
    if getattr(proc, "do_normalize", False) and getattr(proc, "image_mean", None) is not None \
            and getattr(proc, "image_std", None) is not None:
        mean, std = [float(v) for v in proc.image_mean], [float(v) for v in proc.image_std]
    else:
        mean, std = [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]
    units = 255.0 * factor  # the processor's units per unit of the [0, 1] input
    if factor == 1.0:
        out["scale"] = 255
    elif abs(units - 1.0) > 1e-6:
        mean, std = [m / units for m in mean], [s / units for s in std]
    out["mean"], out["std"] = mean, std
    if getattr(proc, "do_flip_channel_order", False):
        out["channels"] = "bgr"
    size = {k: v for k, v in dict(getattr(proc, "size", None) or {}).items() if v is not None}
    if getattr(proc, "do_resize", False) and size:
        if "height" in size and "width" in size:
            h, w = int(size["height"]), int(size["width"])
            if not getattr(proc, "keep_aspect_ratio", False):
                out["resize"] = [h, w]
            elif h == w:  # DPT's keep_aspect_ratio with a square size: the short side goes to that size
                out["resize"] = h
            else:
                log.warning("%s: the image processor resizes to %dx%d keeping the aspect ratio, which the contract "
                            "cannot say; the image keeps its size unless model.resize= is set", where, h, w)
        elif "shortest_edge" in size:
            out["resize"] = int(size["shortest_edge"])
            if size.get("longest_edge"):
                log.warning("%s: the image processor caps the long side at %s; the contract resizes the short side "
                            "to %s without that cap (set model.resize=[H,W] to match it on wide images)", where,
                            size["longest_edge"], size["shortest_edge"])
        else:
            log.warning("%s: the image processor's size %s is not one the contract can say; the image keeps its size "
                        "unless model.resize= is set", where, size)
    if getattr(proc, "do_pad", None) is not False:  # DPT keeps a size_divisor it only uses with do_pad
        for key in ("size_divisor", "size_divisibility"):
            value = getattr(proc, key, None)
            if isinstance(value, int) and not isinstance(value, bool) and value > 1:
                out["pad_multiple"] = value
                break
    if getattr(proc, "do_center_crop", False):
        log.info("%s: the image processor's center crop is not applied: the whole image is segmented", where)
    return out


def _image_processor(cfg: dict[str, Any], source: str, model_type: str, where: str) -> Any | None:
    """The checkpoint's image processor, or None when it has none (no preprocessor_config.json in the folder, or
    none in the hub repo). One that is there but does not load is an error: the input would be a guess."""
    from transformers import AutoImageProcessor

    # OneFormer's processor would fetch its training class list (class_info_file) from the hub; inference needs none
    extra = {"class_info_file": None} if model_type == "oneformer" else {}
    shown = Path(source) / "preprocessor_config.json" if cfg.get("path") else f"of '{source}'"
    if cfg.get("path") and not shown.is_file():
        log.info("%s: model.path=%s has no preprocessor_config.json; the input follows the contract's defaults "
                 "and model.mean/std/resize/pad_multiple", where, source)
        return None
    try:
        return AutoImageProcessor.from_pretrained(source, revision=cfg.get("revision"), **extra)
    except OSError as exc:
        if cfg.get("path"):
            raise ModelError(f"{where}: cannot read the image processor {shown} ({reason(exc)[:300]}); fix or "
                             "remove it (then set model.mean/std/resize/pad_multiple)") from None
        log.info("%s: no image processor for '%s' (%s); the input follows the contract's defaults", where, source,
                 reason(exc)[:200])
        return None
    except Exception as exc:  # a processor that is there but does not load
        raise ModelError(f"{where}: cannot read the image processor {shown} ({reason(exc)[:300]}); fix or remove "
                         "it (then set model.mean/std/resize/pad_multiple)") from None


def _task_inputs(cfg: dict[str, Any], source: str, config: Any, where: str) -> Any:
    """OneFormer's semantic task input: 'the task is semantic' through the checkpoint's CLIP tokenizer, as
    OneFormerProcessor makes it (token ids times the attention mask, padded to the config's task_seq_len)."""
    import torch
    from transformers import AutoTokenizer

    length = int(getattr(config, "task_seq_len", 77))
    shown = f"model.path={source}" if cfg.get("path") else f"'{source}'"
    why = None
    try:
        tokenizer = AutoTokenizer.from_pretrained(source, revision=cfg.get("revision"), trust_remote_code=False)
        words = tokenizer.tokenize(ONEFORMER_TASK)
        tokens = tokenizer([ONEFORMER_TASK], padding="max_length", max_length=length, truncation=True)
    except Exception as exc:  # no tokenizer files, or broken ones
        why = reason(exc)[:200]
    else:  # without its files transformers builds an empty CLIP tokenizer: every word unknown, the task lost
        if not words or tokenizer.unk_token in words:
            why = f"its tokenizer does not know the words: {' '.join(words[:6])}"
    if why is not None:
        raise ModelError(f"{where}: OneFormer needs its task input '{ONEFORMER_TASK}', tokenized by the CLIP tokenizer "
                         f"saved with it, and {shown} has none ({why}); save the model's OneFormerProcessor into the "
                         "folder too (processor.save_pretrained(DIR))")
    ids = torch.tensor(tokens["input_ids"]) * torch.tensor(tokens["attention_mask"])
    return ids.view(1, length)


@contextlib.contextmanager
def _quiet_transformers() -> Iterator[None]:
    """transformers' warnings (its multi-line load report) off while the model loads, its verbosity restored."""
    from transformers.utils import logging as hf_logging

    level = hf_logging.get_verbosity()
    hf_logging.set_verbosity_error()
    try:
        yield
    finally:
        hf_logging.set_verbosity(level)


def _modules():
    """The two wrappers, built on first use (torch is imported by a load, not by the config check)."""
    import torch

    from pairedgta.models.hf_common import query_class_scores

    class SemanticLogits(torch.nn.Module):
        """A semantic model's logits (at its own resolution: the contract upsamples)."""

        def __init__(self, model: torch.nn.Module) -> None:
            super().__init__()
            self.model = model

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.model(pixel_values=x).logits

    class QueryProbabilities(torch.nn.Module):
        """A query-based model's class distribution (not yet renormalised: the contract does that after upsampling)."""

        def __init__(self, model: torch.nn.Module, task_inputs: torch.Tensor | None, where: str) -> None:
            super().__init__()
            self.model, self.where = model, where
            self.register_buffer("task_inputs", task_inputs, persistent=False)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            extra = {} if self.task_inputs is None else {"task_inputs": self.task_inputs.expand(x.shape[0], -1)}
            out = self.model(pixel_values=x, **extra)
            cls, masks = getattr(out, "class_queries_logits", None), getattr(out, "masks_queries_logits", None)
            if cls is None or masks is None:
                raise ModelError(f"{self.where}: the universal model's output ({type(out).__name__}) has no "
                                 "class_queries_logits / masks_queries_logits; model=hf turns Mask2Former, MaskFormer "
                                 "and OneFormer query outputs into classes")
            return query_class_scores(cls, masks)

    return SemanticLogits, QueryProbabilities


def load(name: str, device: str, /, *, path: str | None = None, hub_id: str | None = None,
         revision: str | None = None) -> Network:
    """The checkpoint's model (semantic or universal, from its config), its processor's input and its class names."""
    cfg = {"name": name, "path": path, "hub_id": hub_id, "revision": revision}
    where = f"model ({name})"
    source = pretrained_source(cfg)  # one line: a path that is no folder, or neither key
    shown = f"model.path={source}" if path else f"hub id '{source}'" + (f" (revision {revision})" if revision else "")
    if path and not (Path(source) / "config.json").is_file():
        raise ModelError(f"{where}: model.path={source} has no config.json; point it at a folder that "
                         "model.save_pretrained(DIR) wrote (config.json and model.safetensors)")
    import transformers
    from transformers import AutoConfig, AutoModelForSemanticSegmentation, AutoModelForUniversalSegmentation
    from transformers import PreTrainedModel

    def read_config(src: str) -> Any:
        return AutoConfig.from_pretrained(src, revision=revision, trust_remote_code=False)

    if path:
        try:
            config = read_config(source)
        except Exception as exc:  # not JSON, or a model_type this transformers does not know / that needs remote code
            raise ModelError(f"{where}: transformers {transformers.__version__} cannot read "
                             f"{Path(source) / 'config.json'} ({reason(exc)[:300]}); is it a transformers checkpoint's "
                             "config, and is transformers recent enough for it?") from None
    else:
        config = guarded_pretrained(cfg, read_config)
    kind = _kind(config, where, shown)
    auto = AutoModelForUniversalSegmentation if kind == "universal" else AutoModelForSemanticSegmentation
    kwargs: dict[str, Any] = {"config": config, "revision": revision, "trust_remote_code": False,
                              "output_loading_info": True}
    if path:
        safetensors = any(Path(source).glob("*.safetensors"))
        kwargs["use_safetensors"] = safetensors  # a folder with only pytorch_model.bin: torch.load(weights_only)
        weights = "safetensors weights" if safetensors else "torch weights (weights_only)"
    else:
        weights = "weights (safetensors where the repo has them, else torch weights with weights_only)"
    if "weights_only" in inspect.signature(PreTrainedModel.from_pretrained).parameters:
        kwargs["weights_only"] = True
    with _quiet_transformers():  # its load report would print a table; missing weights are our one line below
        model, info = guarded_pretrained(cfg, lambda s: auto.from_pretrained(s, **kwargs))
    mismatched = [str(m[0] if isinstance(m, (tuple, list)) else m) for m in info.get("mismatched_keys") or []]
    missing = sorted(info.get("missing_keys") or []) + sorted(mismatched)
    if missing:
        shown_keys = ", ".join(missing[:4]) + (", ..." if len(missing) > 4 else "")
        archs = ", ".join(getattr(config, "architectures", None) or []) or "none"
        raise ModelError(f"{where}: {shown} lacks {len(missing)} weights of {type(model).__name__} ({shown_keys}), "
                         f"which would be random; is it a segmentation checkpoint (its architectures: {archs})?")
    if info.get("unexpected_keys"):
        log.info("%s: %d weights of %s are not used by %s (e.g. %s)", where, len(info["unexpected_keys"]), shown,
                 type(model).__name__, sorted(info["unexpected_keys"])[0])
    model = model.float().eval()
    semantic, universal = _modules()
    declared = {}
    proc = _image_processor(cfg, source, config.model_type, where)
    if proc is not None:
        declared = processor_contract(proc, where)
    executes = f"transformers {type(model).__name__}.from_pretrained of {weights} from {shown}; no remote code"
    if kind == "universal":
        task = None
        if "task_inputs" in inspect.signature(model.forward).parameters:
            task = _task_inputs(cfg, source, config, where)
            executes += f"; its tokenizer for the task input '{ONEFORMER_TASK}'"
        module = universal(model, task, where)
        declared["output"] = "probabilities"
    else:
        module = semantic(model)
    id2label = getattr(config, "id2label", None)
    id2label = {int(k): str(v) for k, v in id2label.items()} if id2label else None
    return Network(module, declared=declared, id2label=id2label, executes=executes)
