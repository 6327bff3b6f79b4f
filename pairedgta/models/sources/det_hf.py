"""`task=detection model=hf`: a transformers checkpoint that AutoModelForObjectDetection loads (DETR, Deformable
DETR, Conditional DETR, RT-DETR, D-FINE, YOLOS, ...), from a save_pretrained folder (`model.path`, offline) or the
hub (`model.hub_id`, `model.revision`), with its image processor.

What loading runs: transformers' own classes for the config's model_type, never remote code; no backbone download
(`use_pretrained_backbone=False`: the checkpoint holds the backbone); the weights are data and must hold every weight
of the model (a head from_pretrained would initialise at random is an error). The processor declares the input
(mean/std, short side, channel order) and decodes the outputs (`post_process_object_detection`, each family's own:
softmax with a no-object slot, or sigmoid with top-k); the config's id2label names the classes."""
from __future__ import annotations

import inspect
import logging
from pathlib import Path
from typing import Any

from pairedgta.models.detector_contract import DetectorNetwork
from pairedgta.errors import ModelError, reason

log = logging.getLogger("pairedgta.detection")
LAYOUT = {"preset": "torchvision", "background": "none"}  # the processor's per-image dicts, ids of id2label


def _wrapper():
    import torch

    class PostProcessed(torch.nn.Module):
        """The model and its processor's decoding: a prepared batch -> per image boxes (pixels of the input)."""

        def __init__(self, model: torch.nn.Module, processor: Any) -> None:
            super().__init__()
            self.model, self.processor = model, processor

        def forward(self, x: torch.Tensor) -> list[dict[str, torch.Tensor]]:
            out = self.model(pixel_values=x)
            sizes = [tuple(x.shape[-2:])] * x.shape[0]
            return self.processor.post_process_object_detection(out, threshold=0.0, target_sizes=sizes)

    return PostProcessed


def load(name: str, device: str, /, *, path: str | None = None, hub_id: str | None = None,
         revision: str | None = None) -> DetectorNetwork:
    from pairedgta.models.hf_common import guarded_pretrained, pretrained_source
    from pairedgta.models.sources.hf import _image_processor, _quiet_transformers, processor_contract

    cfg = {"name": name, "path": path, "hub_id": hub_id, "revision": revision}
    where = f"model ({name})"
    source = pretrained_source(cfg)
    shown = f"model.path={source}" if path else f"hub id '{source}'"
    if path and not (Path(source) / "config.json").is_file():
        raise ModelError(f"{where}: model.path={source} has no config.json; point it at a folder that "
                         "model.save_pretrained(DIR) wrote (config.json and model.safetensors)")
    import transformers
    from transformers import AutoConfig, AutoModelForObjectDetection, PreTrainedModel
    from transformers.models.auto.modeling_auto import MODEL_FOR_OBJECT_DETECTION_MAPPING_NAMES

    try:
        config = guarded_pretrained(cfg, lambda s: AutoConfig.from_pretrained(s, revision=revision,
                                                                              trust_remote_code=False))
    except ModelError:
        raise
    except Exception as exc:
        raise ModelError(f"{where}: transformers {transformers.__version__} cannot read the config of {shown} "
                         f"({reason(exc)[:300]})") from None
    if config.model_type not in MODEL_FOR_OBJECT_DETECTION_MAPPING_NAMES:
        raise ModelError(f"{where}: {shown} is a '{config.model_type}' model, which AutoModelForObjectDetection does "
                         f"not load; task=detection model=hf takes {', '.join(MODEL_FOR_OBJECT_DETECTION_MAPPING_NAMES)}"
                         " (a segmentation checkpoint runs with task=segmentation)")
    if hasattr(config, "use_pretrained_backbone"):
        config.use_pretrained_backbone = False  # timm/torchvision backbones would download ImageNet weights
    for sub in ("backbone_config",):
        inner = getattr(config, sub, None)
        if inner is not None and hasattr(inner, "use_pretrained_backbone"):
            inner.use_pretrained_backbone = False
    kwargs: dict[str, Any] = {"config": config, "revision": revision, "trust_remote_code": False,
                              "output_loading_info": True}
    if path:
        kwargs["use_safetensors"] = any(Path(source).glob("*.safetensors"))
    if "weights_only" in inspect.signature(PreTrainedModel.from_pretrained).parameters:
        kwargs["weights_only"] = True
    with _quiet_transformers():
        model, info = guarded_pretrained(cfg, lambda s: AutoModelForObjectDetection.from_pretrained(s, **kwargs))
    mismatched = [str(m[0] if isinstance(m, (tuple, list)) else m) for m in info.get("mismatched_keys") or []]
    missing = sorted(info.get("missing_keys") or []) + sorted(mismatched)
    if missing:
        raise ModelError(f"{where}: {shown} lacks {len(missing)} weights of {type(model).__name__} "
                         f"({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}), which would be random; is it "
                         "an object-detection checkpoint?")
    processor = _image_processor(cfg, source, config.model_type, where)
    if processor is None or not hasattr(processor, "post_process_object_detection"):
        raise ModelError(f"{where}: {shown} has no object-detection image processor (preprocessor_config.json); "
                         "save it beside the model: AutoImageProcessor.from_pretrained(...).save_pretrained(DIR)")
    declared = processor_contract(processor, where)
    declared.pop("pad_multiple", None)
    declared["layout"] = LAYOUT
    id2label = {int(k): str(v) for k, v in (getattr(config, "id2label", None) or {}).items()} or None
    module = _wrapper()(model.float().eval(), processor)
    return DetectorNetwork(module, declared=declared, id2label=id2label,
                           executes=f"transformers {type(model).__name__}.from_pretrained from {shown}; no remote code")
