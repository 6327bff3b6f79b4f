"""Package data: reference measurements shipped with the code (see README.md in this folder)."""
from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
PAPER_GENERATION_TIMES = DATA_DIR / "paper_generation_times.csv"
PAPER_TABLE1 = DATA_DIR / "paper_table1.csv"
DEEPGTAV_SUVS = DATA_DIR / "deepgtav_suvs.csv"  # SUVs the DeepGTAV plugin types Truck (its header names the source)
GTA_PHOTOMETRY = DATA_DIR / "gta_photometry.csv"  # measured from the authors' GTA V frames (gta_photometry.md)
