"""Tiny detectors for the detector-source tests: a user's own code, as `task=detection model=python
model.target=detector_nets:<fn>` (the tests directory is on sys.path under pytest), and the same networks exported
to the other formats (ONNX, torch.export)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pairedgta.detection.boxes import INSTANCE_CLASSES


class TinyYolo(torch.nn.Module):
    """A YOLOv8-style head (B, 4 + C, N): one box per stride-8 cell, cxcywh pixels of the input, sigmoid class
    scores, no objectness and no NMS. Made to give well-separated scores (no ties, so every format keeps the same
    boxes through NMS): the class logits carry a per-cell ramp."""

    def __init__(self, classes: int = 8, width: int = 8) -> None:
        super().__init__()
        self.classes = classes
        self.stem = torch.nn.Conv2d(3, width, 3, stride=2, padding=1)
        self.mid = torch.nn.Conv2d(width, width, 3, stride=2, padding=1)
        self.out = torch.nn.Conv2d(width, width, 3, stride=2, padding=1)
        self.box = torch.nn.Conv2d(width, 4, 1)
        self.cls = torch.nn.Conv2d(width, classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.relu(self.out(torch.relu(self.mid(torch.relu(self.stem(x))))))
        b, _, h, w = f.shape
        ys = (torch.arange(h, dtype=x.dtype, device=x.device) + 0.5) * 8
        xs = (torch.arange(w, dtype=x.dtype, device=x.device) + 0.5) * 8
        cy, cx = ys.view(1, h, 1).expand(b, h, w), xs.view(1, 1, w).expand(b, h, w)
        d = self.box(f)
        cx = cx + 4 * torch.tanh(d[:, 0])
        cy = cy + 4 * torch.tanh(d[:, 1])
        bw = 12 * torch.exp(d[:, 2].clamp(-1, 1))
        bh = 20 * torch.exp(d[:, 3].clamp(-1, 1))
        ramp = torch.linspace(-2.0, 2.0, h * w, dtype=x.dtype, device=x.device).view(1, 1, h, w)
        logits = self.cls(f) + ramp
        boxes = torch.stack([cx, cy, bw, bh], dim=1)
        return torch.cat([boxes, torch.sigmoid(logits)], dim=1).flatten(2)  # B x (4 + C) x N


def tiny_yolo(classes: int = 8, width: int = 8, seed: int = 0) -> TinyYolo:
    torch.manual_seed(seed)
    return TinyYolo(classes, width).eval()


def zoo_fcos() -> torch.nn.Module:
    """The zoo's reference detector as a user's own torchvision-style module (weights given as checkpoint_path)."""
    from pairedgta.models.detectors import NUM_CLASSES, fcos

    return fcos("zoo_fcos", NUM_CLASSES, 512, 1024, width=0.5, fpn_channels=64).eval()


def ssdlite(num_classes: int = 91) -> torch.nn.Module:
    """torchvision's SSDlite as a user's factory: the same network model=torchvision builds."""
    import torchvision

    return torchvision.models.detection.ssdlite320_mobilenet_v3_large(weights=None, weights_backbone=None,
                                                                      num_classes=num_classes)


CITYSCAPES_CLASSES = len(INSTANCE_CLASSES)


def _red_box(image: torch.Tensor, red: int) -> torch.Tensor | None:
    """xyxy of the pixels that are red in channel `red` (bright there, dark in the others), or None."""
    others = [c for c in range(3) if c != red]
    mask = (image[red] > 0.8) & (image[others[0]] < 0.2) & (image[others[1]] < 0.2)
    if not mask.any():
        return None
    ys, xs = torch.nonzero(mask, as_tuple=True)
    return torch.stack([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]).float()


class RedCarBGR(torch.nn.Module):
    """A torchvision-style 'detector' trained on BGR input: a red block is a car. Fed RGB, it sees blue where the red
    is and finds nothing; the set-up check must name model.channels=bgr."""

    def forward(self, images: list[torch.Tensor]) -> list[dict[str, torch.Tensor]]:
        out = []
        for image in images:
            box = _red_box(image, red=2)
            boxes = box[None] if box is not None else torch.zeros(0, 4)
            out.append({"boxes": boxes, "scores": torch.full((len(boxes),), 0.9),
                        "labels": torch.full((len(boxes),), 3, dtype=torch.int64)})  # background 0: 3 is car
        return out


class RedCarCenter(torch.nn.Module):
    """The same idea as a YOLOv8-style head over RGB input: one box, centre-xywh pixels, 8 class scores."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows = []
        for image in x:
            box = _red_box(image, red=0)
            if box is None:
                rows.append(torch.zeros(12, 1))
                continue
            cxcywh = torch.stack([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2, box[2] - box[0], box[3] - box[1]])
            scores = torch.zeros(8)
            scores[2] = 0.9
            rows.append(torch.cat([cxcywh, scores])[:, None])
        return torch.stack(rows)


def red_car_bgr() -> RedCarBGR:
    return RedCarBGR()


def red_car_center() -> RedCarCenter:
    return RedCarCenter()


def street(seed: int = 0, size=(256, 512)) -> np.ndarray:
    """A street-like test image: sky, road, and a few car- and person-shaped blocks."""
    rng = np.random.default_rng(seed)
    h, w = size
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2] = (135, 170, 210)
    img[h // 2:] = (90, 90, 95)
    for _ in range(6):
        x, y = int(rng.integers(0, w - 60)), int(rng.integers(h // 2 - 20, h - 40))
        img[y:y + 30, x:x + 55] = rng.integers(20, 230, 3)
        px = int(rng.integers(0, w - 12))
        img[h // 2 - 10:h // 2 + 30, px:px + 10] = (200, 160, 120)
    return img


def tiny_detr_dir(folder: Path, id2label: dict[int, str]) -> Path:
    """A random DETR with a tiny ResNet backbone (no timm, nothing downloaded) and its processor, saved."""
    from transformers import DetrConfig, DetrForObjectDetection, DetrImageProcessor, ResNetConfig

    backbone = ResNetConfig(embedding_size=8, hidden_sizes=[8, 16, 16, 16], depths=[1, 1, 1, 1],
                            out_features=["stage4"])
    config = DetrConfig(use_timm_backbone=False, backbone_config=backbone, use_pretrained_backbone=False, d_model=16,
                        encoder_layers=1, decoder_layers=1, encoder_attention_heads=2, decoder_attention_heads=2,
                        encoder_ffn_dim=32, decoder_ffn_dim=32, num_queries=12, id2label=id2label,
                        label2id={v: k for k, v in id2label.items()})
    torch.manual_seed(0)
    model = DetrForObjectDetection(config).eval()
    with torch.no_grad():  # the last class rarely wins, so the instance classes show up in a random model
        model.class_labels_classifier.bias[len(id2label) - 1] -= 4.0
    model.save_pretrained(folder)
    DetrImageProcessor(size={"shortest_edge": 96, "longest_edge": 192}).save_pretrained(folder)
    return folder
