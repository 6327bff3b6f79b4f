"""Halve the zoo's float32 weights to float16, so the package stays under PyPI's 100 MB file limit with
20+ members (experiments/train_demo_model.py writes float16 since; this converts the members trained before).

    python experiments/halve_zoo_weights.py            # every member under pairedgta/models/weights/

Each model.safetensors is rewritten (temporary name, then rename) with its floating tensors in float16; the
loaders compute in float32 (a SegFormer folder's config keeps dtype float32, so transformers upcasts). The
model card gains `weights_dtype: float16` and its README says so. A member already in float16 is left as it is."""
from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_demo_model import WEIGHTS_LINE as LINE, halve_safetensors  # noqa: E402

from pairedgta.jsonio import write_json  # noqa: E402

WEIGHTS = Path(__file__).resolve().parents[1] / "pairedgta" / "models" / "weights"


def is_half(path: Path) -> bool:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return all(not f.get_slice(k).get_dtype().startswith("F") or f.get_slice(k).get_dtype() == "F16"
                   for k in f.keys())


def main() -> None:
    for folder in sorted(p for p in WEIGHTS.iterdir() if (p / "model.safetensors").is_file()):
        weights, card_path, readme = folder / "model.safetensors", folder / "model_card.json", folder / "README.md"
        before = weights.stat().st_size
        if not is_half(weights):
            halve_safetensors(weights)
        card = json.loads(card_path.read_text())
        if card.get("weights_dtype") != "float16":
            card["weights_dtype"] = "float16"
            write_json(card_path, card)
        text = readme.read_text()
        if LINE not in text:
            lines = text.split("\n")
            at = next((i for i, line in enumerate(lines) if line.startswith("- wall time:")), len(lines))
            readme.write_text("\n".join(lines[:at] + [LINE] + lines[at:]))
        for f in (weights, card_path, readme):
            f.chmod(0o644)
        print(f"{folder.name}: {before / 2**20:.1f} -> {weights.stat().st_size / 2**20:.1f} MiB")
    total = sum(f.stat().st_size for f in WEIGHTS.rglob("*") if f.is_file())
    print(f"weights in all: {total / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
