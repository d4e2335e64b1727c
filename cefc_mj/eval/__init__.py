"""Evaluation: episodes on either backend, the paper's tables, regression bands, recordings."""

from cefc_mj.nn.registry import DEFAULT_LOWLEVEL as DEFAULT_POLICY

__all__ = ["DEFAULT_POLICY"]
