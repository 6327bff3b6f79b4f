"""PairedGTA: perfectly paired photometric shifts for segmentation robustness."""

__version__ = "0.1.0"
