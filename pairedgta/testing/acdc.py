"""An ACDC stand-in: a generated dataset copied into ACDC's tree and file naming (pairedgta/datasets/acdc.py), with
the adverse frames' objects as ACDC's panoptic labels, for demos and tests on machines without ACDC. It is not ACDC.

    python -c "from pairedgta.testing.acdc import write_standin; write_standin('<generate dir>', 'outputs/acdc_standin',
               'Day-EXTRASUNNY', 'Night-EXTRASUNNY')"
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from pairedgta.datasets.acdc import adverse_path, label_path, panoptic_path, reference_path


def write_standin(
    generated_root: str | Path, out: str | Path, clean: str, adverse: str, condition: str = "night",
    val_share: float = 0.2, frames_per_sequence: int = 5,
) -> Path:
    """Copy a generated dataset into ACDC's layout and file naming: `clean` images become the
    references, `adverse` images (and their labels, as ground truth) the adverse frames; where the adverse
    image has its instance mask, its objects become ACDC's panoptic labels (PNG + one JSON per split), which
    the detection task reads as boxes.

    A stand-in for demos and tests on machines without ACDC (generated with generate.pairing
    perturbations it is coarsely paired like ACDC); it is not ACDC."""
    import json

    generated_root, out = Path(generated_root), Path(out)
    index = json.loads((generated_root / "index.json").read_text())
    scenes = index["scenes"]
    n_val = round(len(scenes) * val_share)
    panoptic: dict[str, dict[str, list]] = {}
    for i, scene in enumerate(scenes):
        split = "val" if i >= len(scenes) - n_val else "train"
        seq = f"GOPR{i // frames_per_sequence:04d}"
        n = f"{i:06d}"
        src = generated_root / scene["dir"]
        pairs = [
            (src / f"{clean}.png", reference_path(out, condition, split, seq, n)),
            (src / f"{adverse}.png", adverse_path(out, condition, split, seq, n)),
            (src / f"{adverse}_labels.png", label_path(out, condition, split, seq, n)),
        ]
        for a, b in pairs:
            if a.is_file():
                b.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(a, b)
        instances, labels = src / f"{adverse}_instances.png", src / f"{adverse}_labels.png"
        if instances.is_file() and labels.is_file():
            entry = panoptic.setdefault(split, {"images": [], "annotations": []})
            image_id = len(entry["images"]) + 1
            png = panoptic_path(out, condition, split, seq, n)
            width, height, segments = _write_panoptic(instances, labels, png)
            entry["images"].append({"id": image_id, "width": width, "height": height,
                                    "file_name": f"{condition}/{split}/{seq}/{seq}_frame_{n}_rgb_anon.png"})
            entry["annotations"].append({"image_id": image_id, "file_name": png.name, "segments_info": segments})
    for split, entry in panoptic.items():
        path = out / "gt_panoptic" / condition / f"{condition}_{split}_gt_panoptic.json"
        path.write_text(json.dumps({**entry, "categories": _panoptic_categories()}))
    return out


def _write_panoptic(instances: Path, labels: Path, png: Path) -> tuple[int, int, list[dict[str, Any]]]:
    """One generated frame's objects as a COCO panoptic PNG (segment id = the instance id) and its segments_info."""
    import numpy as np
    from PIL import Image

    from pairedgta.detection.boxes import boxes_from_instances
    from pairedgta.detection.real_boxes import LABEL_ID_TO_INSTANCE

    label_id = {v: k for k, v in LABEL_ID_TO_INSTANCE.items()}
    inst = np.asarray(Image.open(instances)).astype(np.int64)
    boxes = boxes_from_instances(inst, np.asarray(Image.open(labels)), min_area=0)
    ids = np.where(np.isin(inst, [b.instance for b in boxes]), inst, 0)
    rgb = np.stack([ids % 256, ids // 256 % 256, ids // 65536], axis=-1).astype(np.uint8)
    png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(png)
    segments = [{"id": int(b.instance), "category_id": label_id[b.label], "iscrowd": 0, "area": int(b.area),
                 "bbox": [b.xyxy[0], b.xyxy[1], b.xyxy[2] - b.xyxy[0], b.xyxy[3] - b.xyxy[1]]} for b in boxes]
    return int(inst.shape[1]), int(inst.shape[0]), segments


def _panoptic_categories() -> list[dict[str, Any]]:
    from pairedgta.detection.real_boxes import LABEL_ID_TO_INSTANCE
    from pairedgta.detection.boxes import INSTANCE_CLASSES

    return [{"id": lid, "name": INSTANCE_CLASSES[k], "isthing": 1} for lid, k in LABEL_ID_TO_INSTANCE.items()]
