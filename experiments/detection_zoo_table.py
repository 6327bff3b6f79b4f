"""docs/zoo.md's "Detection zoo" member table, read from the members themselves: each model card
(zoo/detection/pairedgta_detection_zoo/<name>/model_card.json: arch, steps, wall time, held-out AP) and the
comment that opens its recipe (pairedgta/conf/detector_zoo/<name>.yaml), so the table cannot drift from the
weights it describes.

    python experiments/detection_zoo_table.py            # the markdown table, members in +experiment=det_zoo's order
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml
from train_demo_detector import FAMILY_TEXT, ROOT, chain_seconds

ZOO = ROOT / "zoo" / "detection" / "pairedgta_detection_zoo"
RECIPES = ROOT / "pairedgta" / "conf" / "detector_zoo"
ZOO_EXPERIMENT = ROOT / "pairedgta" / "conf" / "experiment" / "det_zoo.yaml"


def recipe_text(name: str) -> str:
    """The recipe's opening comment, one line (what makes this member differ)."""
    lines = []
    for line in (RECIPES / f"{name}.yaml").read_text().splitlines():
        if not line.startswith("#"):
            break
        if "@package" not in line:
            lines.append(line.lstrip("# ").strip())
    return " ".join(lines).replace("|", "/")


def members(zoo: dict) -> list[str]:
    """The whole zoo (+experiment=det_zoo's `models`), its reference last, then any other carded member."""
    listed = [m for m in zoo["models"] if m != zoo["reference_model"]] + [zoo["reference_model"]]
    rest = sorted(p.name for p in ZOO.iterdir() if (p / "model_card.json").is_file() and p.name not in listed)
    return listed + rest


def card(name: str) -> dict:
    return json.loads((ZOO / name / "model_card.json").read_text())


def row(name: str, reference: str, classes: list[str]) -> str:
    card_ = card(name)
    arch, val = card_["arch"], card_["val"]
    size = (ZOO / name / "model.safetensors").stat().st_size / 1e6
    per_class = " | ".join(f"{val['ap50_per_class'][c]:.3f}" for c in classes)
    minutes = card_["train_seconds"] / 60
    start = card_["train"].get("init_from")
    start = f"from `{Path(start).name}`" if start else "from scratch"
    chain = chain_seconds(card_)
    total = f" ({sum(s for _, s in chain) / 60:.0f} min from scratch)" if len(chain) > 2 else ""
    member = f"**`{name}`** (reference)" if name == reference else f"`{name}`"
    return (f"| {member} | {FAMILY_TEXT[card_['family']]} ({arch['width']}, {arch['fpn_channels']}; min_size "
            f"{arch['min_size']}) | {recipe_text(name)} | {card_['parameters'] / 1e6:.2f} M, {size:.1f} MB | "
            f"{card_['train']['steps']:,} steps {start}, {minutes:.0f} min{total} | {per_class} | {val['ap']:.3f} |")


def main() -> None:
    zoo = yaml.safe_load(ZOO_EXPERIMENT.read_text())
    names = members(zoo)
    classes = list(card(names[0])["val"]["gt_per_class"])  # the classes with held-out ground truth, as scored
    print("| member | family (width, FPN; scale) | recipe | size | training | " + " | ".join(
        f"AP50 {c}" for c in classes) + " | AP |")
    print("|---|---|---|---|---|" + "---:|" * (len(classes) + 1))
    for name in names:
        print(row(name, zoo["reference_model"], classes))


if __name__ == "__main__":
    main()
