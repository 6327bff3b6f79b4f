"""Test support that ships with the package, used by tests and benchmarks, never by a run: the DeepGTAV
protocol test server (a stand-in for the game plugin), writers of small datasets in the released layouts,
and helpers that compose the real config or run the real CLI."""
