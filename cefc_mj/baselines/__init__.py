"""Non-learning baselines of the paper's tables (docs/baselines.md): ORCA-F (`orca`)."""
