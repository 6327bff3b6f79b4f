"""Model sources: each loads a researcher's own model from one format into a `Network`
(pairedgta/models/contract.py), which the shared contract and label map turn into 19 Cityscapes probabilities.
One module per source, one registry line each in pairedgta/models/__init__.py; docs/models.md says what each
executes when it loads."""
