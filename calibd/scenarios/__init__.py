"""The ready-made scenarios (`calibd simulate NAME`, `calibd plan --scenario NAME`): one TOML file
here each, named in READY_MADE. A package of its own so the command line names them without
importing the scenario parser (docs/architecture.md, Start-up)."""

READY_MADE = ("thesis-real", "thesis-bench", "continuous")
