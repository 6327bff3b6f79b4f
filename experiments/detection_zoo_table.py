"""docs/zoo.md's "Detection zoo" member table, read from the members themselves: each model card
(zoo/detection/pairedgta_detection_zoo/<name>/model_card.json: arch, steps, wall time, held-out AP) and the
comment that opens its recipe (pairedgta/conf/detector_zoo/<name>.yaml), so the table cannot drift from the
weights it describes.

    python experiments/detection_zoo_table.py            # the markdown table, members in the task's order
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
ZOO = ROOT / "zoo" / "detection" / "pairedgta_detection_zoo"
RECIPES = ROOT / "pairedgta" / "conf" / "detector_zoo"
FAMILY = {"fcos": "FCOS", "retinanet": "RetinaNet", "fasterrcnn": "Faster R-CNN"}
CLASSES = ("person", "rider", "car", "truck", "bus", "motorcycle", "bicycle")


def recipe_text(name: str) -> str:
    """The recipe's opening comment, one line (what makes this member differ)."""
    lines = []
    for line in (RECIPES / f"{name}.yaml").read_text().splitlines():
        if not line.startswith("#"):
            break
        if "@package" not in line:
            lines.append(line.lstrip("# ").strip())
    return " ".join(lines).replace("|", "/")


def members() -> list[str]:
    """The task's zoo (conf/task/detection.yaml `models`), its reference last, then any other carded member."""
    task = yaml.safe_load((ROOT / "pairedgta" / "conf" / "task" / "detection.yaml").read_text())
    listed = [m for m in task["models"] if m != task["reference_model"]] + [task["reference_model"]]
    rest = sorted(p.name for p in ZOO.iterdir() if (p / "model_card.json").is_file() and p.name not in listed)
    return listed + rest


def row(name: str, reference: str) -> str:
    card = json.loads((ZOO / name / "model_card.json").read_text())
    arch, val = card["arch"], card["val"]
    size = (ZOO / name / "model.safetensors").stat().st_size / 1e6
    per_class = " | ".join(f"{val['ap50_per_class'][c]:.3f}" for c in CLASSES)
    minutes = card["train_seconds"] / 60
    start = card["train"].get("init_from")
    start = f"from `{Path(start).name}`" if start else "from scratch"
    member = f"**`{name}`** (reference)" if name == reference else f"`{name}`"
    return (f"| {member} | {FAMILY[card['family']]} ({arch['width']}, {arch['fpn_channels']}; min_size "
            f"{arch['min_size']}) | {recipe_text(name)} | {card['parameters'] / 1e6:.2f} M, {size:.1f} MB | "
            f"{card['train']['steps']:,} steps {start}, {minutes:.0f} min | {per_class} | {val['ap']:.3f} |")


def main() -> None:
    task = yaml.safe_load((ROOT / "pairedgta" / "conf" / "task" / "detection.yaml").read_text())
    print("| member | family (width, FPN; scale) | recipe | size | training | " + " | ".join(
        f"AP50 {c}" for c in CLASSES) + " | AP |")
    print("|---|---|---|---|---|" + "---:|" * (len(CLASSES) + 1))
    for name in members():
        print(row(name, task["reference_model"]))


if __name__ == "__main__":
    main()
