"""Physical models behind the simulated devices; sources in docs/models.md."""
