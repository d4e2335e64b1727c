"""Non-learning baselines of the paper's tables (docs/research/baselines.md): ORCA-F (`orca`)."""
