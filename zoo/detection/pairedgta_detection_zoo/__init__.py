"""The detection zoo's weights, one folder per member (`model=<name>`; model cards inside). A distribution apart
from pairedgta so that neither wheel passes a package index's 100 MB: pairedgta resolves
`pkg://models/weights/<name>/...` to this folder when the file is not in its own package (pairedgta/models/hf_common.py)."""
from pathlib import Path

WEIGHTS = Path(__file__).resolve().parent
