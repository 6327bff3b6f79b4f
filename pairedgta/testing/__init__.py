"""Stand-ins for external systems (the DeepGTAV plugin), used by tests and benchmarks, never by a run."""
