"""Errors that the command-line tools turn into one clear line (exit code 2) instead of a traceback."""


class CefcError(Exception):
    """Base class of the project's user-facing errors."""


class ConfigError(CefcError, ValueError):
    """A configuration value, CLI flag or input array is invalid. The message names the argument."""


class CheckpointError(CefcError, ValueError):
    """A checkpoint file is missing, tampered with, or made for another observation/action shape."""


class SimulationDiverged(CefcError, RuntimeError):
    """The physics produced NaN/inf or a drone flipped; the episode is stopped and reported."""
