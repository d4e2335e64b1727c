"""Errors that the command-line tools turn into one clear line (exit code 2) instead of a traceback."""

import argparse
import sys


class CefcError(Exception):
    """Base class of the project's user-facing errors."""


class ConfigError(CefcError, ValueError):
    """A configuration value, CLI flag or input array is invalid. The message names the argument."""


class CheckpointError(CefcError, ValueError):
    """A checkpoint file is missing, tampered with, or made for another observation/action shape."""


class SimulationDiverged(CefcError, RuntimeError):
    """The physics produced NaN/inf or a drone flipped; the episode is stopped and reported."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, `<prog>: error: <message>`, with exit code 2
    (the project's convention for bad input; the usage is in --help)."""

    def error(self, message: str):  # noqa: D102 (argparse API)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)
