"""Detector sources (`task=detection model=<source>`): each loads a researcher's own detector from one format into a
`DetectorNetwork` (pairedgta/detection/contract.py), which the shared contract, layout and label space turn into
boxes of the eight Cityscapes instance classes. One module per source, one registry line each in
pairedgta/models/__init__.py; docs/models.md says what each executes when it loads."""
