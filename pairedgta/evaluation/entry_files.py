"""The names of an evaluate entry's own files (its metrics name theirs): below both `entry`, which writes and reads
them, and `registry`, whose `result_files` lists every file of an entry, so neither imports the other for them."""
from __future__ import annotations

SUMMARY, GROUP_COUNTS, PREDICTIONS = "summary.json", "group_counts.npz", "predictions.npz"
OWN_FILES = (SUMMARY, GROUP_COUNTS)  # the entry's tables besides the metrics' (predictions.npz: label maps)

__all__ = ["SUMMARY", "GROUP_COUNTS", "PREDICTIONS", "OWN_FILES"]
