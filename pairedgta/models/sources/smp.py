"""`model=smp`: a segmentation_models_pytorch model saved with `model.save_pretrained(DIR)` (config.json and
model.safetensors), `model.path=DIR`.

smp.from_pretrained is not used: it builds the model with config.json's encoder_weights, and a model trained from an
ImageNet encoder says encoder_weights="imagenet", so it would download that encoder only to overwrite it (and fail
offline). Here the architecture config.json names (`_model_class`) is built from config.json with
encoder_weights=None (nothing fetched) and activation=None (the logits: the contract applies the softmax, and smp's
activations hold no weights), then the folder's weights are loaded strictly, as data: model.safetensors, or
pytorch_model.bin through torch.load(weights_only=True). The input is padded to the encoder's output stride, the
multiple smp's own check_input_shape asks for; mean/std stay the contract's ImageNet default (smp's encoders are
ImageNet-pretrained; model.mean/std= say otherwise)."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from pairedgta.errors import ModelError, reason
from pairedgta.models.contract import Network

log = logging.getLogger("pairedgta.models")
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")  # what smp's save_pretrained writes, newest first
_SHOW = 4


def _folder(path: str | None, where: str) -> Path:
    if not path:
        raise ModelError(f"{where}: model=smp needs its folder; set model.path=DIR, a folder that "
                         "model.save_pretrained(DIR) wrote (config.json and model.safetensors)")
    folder = Path(str(path)).expanduser()
    if not folder.exists():
        raise ModelError(f"{where}: model.path={path} does not exist; point it at the folder that "
                         "model.save_pretrained(DIR) wrote")
    if not folder.is_dir():
        raise ModelError(f"{where}: model.path={path} is a file, not a folder; point it at the folder that "
                         "model.save_pretrained(DIR) wrote (config.json and model.safetensors)")
    return folder


def _config(folder: Path, where: str) -> dict[str, Any]:
    file = folder / "config.json"
    if not file.is_file():
        raise ModelError(f"{where}: model.path={folder} has no config.json; save the model with "
                         "model.save_pretrained(DIR), which writes config.json beside model.safetensors")
    try:
        config = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ModelError(f"{where}: {file} is not readable JSON ({reason(exc)[:200]}); save the model again with "
                         "model.save_pretrained(DIR)") from None
    if not isinstance(config, dict):
        raise ModelError(f"{where}: {file} holds {type(config).__name__}, not the init arguments smp's "
                         "save_pretrained writes; save the model again with model.save_pretrained(DIR)")
    return config


def build_from_config(config: dict[str, Any], file: Path, where: str) -> Any:
    """The architecture `_model_class` names, with config.json's init arguments, no encoder download, no activation."""
    import segmentation_models_pytorch as smp

    archs = {cls.__name__: cls for cls in smp.MODEL_ARCHITECTURES_MAPPING.values()} \
        if hasattr(smp, "MODEL_ARCHITECTURES_MAPPING") else {}
    arch = config.get("_model_class")
    if arch not in archs:
        raise ModelError(f"{where}: {file} names _model_class={arch!r}, not a segmentation_models_pytorch "
                         f"{smp.__version__} architecture ({', '.join(sorted(archs))}); save the model with smp's "
                         "model.save_pretrained(DIR)")
    kwargs = {k: v for k, v in config.items() if not k.startswith("_")}
    if kwargs.get("in_channels", 3) != 3:
        raise ModelError(f"{where}: {file} has in_channels={kwargs['in_channels']}; the images are RGB, 3 channels")
    if kwargs.get("activation") is not None:
        log.info("%s: %s's activation %r is left out: the contract takes the logits", where, arch,
                 kwargs["activation"])
    kwargs.update(encoder_weights=None, activation=None)
    try:
        return archs[arch](**kwargs)
    except Exception as exc:  # an unknown encoder, an argument this smp does not take, a size that does not fit
        raise ModelError(f"{where}: smp.{arch}(**config.json) fails ({reason(exc)[:300]}); is {file} from this "
                         f"segmentation_models_pytorch ({smp.__version__})?") from None


def _listing(keys: list[str]) -> str:
    return ", ".join(keys[:_SHOW]) + (", ..." if len(keys) > _SHOW else "")


def load_weights(module: Any, folder: Path, where: str) -> Path:
    """The folder's weights into `module`, every key accounted for (read as data: pairedgta/models/checkpoint.py)."""
    from pairedgta.models.checkpoint import read_state_dict

    file = next((folder / n for n in WEIGHT_FILES if (folder / n).is_file()), None)
    if file is None:
        raise ModelError(f"{where}: model.path={folder} has no weights ({' or '.join(WEIGHT_FILES)}); save the "
                         "model with model.save_pretrained(DIR)")
    state = read_state_dict(file, model_name=where)
    expected = module.state_dict()
    missing = sorted(k for k in expected if k not in state)
    unexpected = sorted(k for k in state if k not in expected)
    mismatched = [f"{k} file {list(state[k].shape)} vs model {list(expected[k].shape)}"
                  for k in sorted(expected) if k in state and tuple(state[k].shape) != tuple(expected[k].shape)]
    if missing or unexpected or mismatched:
        parts = [f"{len(keys)} {what} ({_listing(keys)})" for what, keys in
                 (("missing", missing), ("unexpected", unexpected), ("shape mismatches", mismatched)) if keys]
        raise ModelError(f"{where}: {file} does not fit the model config.json describes: {'; '.join(parts)}; were "
                         "both saved together by model.save_pretrained(DIR)?")
    module.load_state_dict(state, strict=True)
    return file


def load(name: str, device: str, /, *, path: str | None = None) -> Network:
    """config.json's architecture with the folder's weights; padded to its encoder's output stride."""
    where = f"model ({name})"
    folder = _folder(path, where)
    config = _config(folder, where)
    module = build_from_config(config, folder / "config.json", where)
    file = load_weights(module, folder, where)
    stride = int(getattr(getattr(module, "encoder", None), "output_stride", 32) or 32)
    weights = "safetensors weights" if file.suffix == ".safetensors" else "torch weights (weights_only)"
    return Network(module.eval(), declared={"pad_multiple": stride},
                   executes=f"segmentation_models_pytorch {config['_model_class']} built from config.json "
                            f"(encoder_weights=None: nothing fetched), {weights} from {file}")
