"""Test support that ships with the package: the DeepGTAV protocol test server, writers of small
datasets in the released layouts, and helpers that compose the real config or run the real CLI."""
