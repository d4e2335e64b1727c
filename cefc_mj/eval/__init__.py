"""Evaluation: episodes on either backend, the paper's tables, regression bands, recordings."""

DEFAULT_POLICY = "nav"
"""The low level the evaluators fly when no --policy is given: AT-M-Nav of each c, the Step 3 policy
fine-tuned with a larger navigation weight (docs/decisions.md). "atm" flies the paper's Step 3."""
