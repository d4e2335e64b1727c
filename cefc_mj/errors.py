"""Errors that the command-line tools turn into one clear line (exit code 2) instead of a traceback."""

import argparse
import sys
import textwrap


class CefcError(Exception):
    """Base class of the project's user-facing errors."""


class ConfigError(CefcError, ValueError):
    """A configuration value, CLI flag or input array is invalid. The message names the argument."""


class CheckpointError(CefcError, ValueError):
    """A checkpoint file is missing, tampered with, or made for another observation/action shape."""


class SimulationDiverged(CefcError, RuntimeError):
    """The physics produced NaN/inf or a drone flipped; the episode is stopped and reported."""


class ExamplesHelpFormatter(argparse.HelpFormatter):
    """argparse's help, except that a paragraph of the description or epilog with a line indented by two
    spaces (an example command and its comment) is kept as written; other paragraphs are filled to the
    terminal's width as usual. Lets a --help end with examples and a docs pointer (`help_epilog`)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        out = []
        for paragraph in text.strip("\n").split("\n\n"):
            lines = paragraph.splitlines()
            if any(line.startswith("  ") for line in lines):
                out.append("\n".join(indent + line for line in lines))
            else:  # as argparse fills, without breaking a command or a path at its hyphens
                words = " ".join(paragraph.split())
                out.append(
                    textwrap.fill(words, width, initial_indent=indent, subsequent_indent=indent, break_on_hyphens=False)
                )
        return "\n\n".join(out)


def help_epilog(examples: list[str] | tuple[str, ...], docs: str) -> str:
    """The end of a --help (with `ExamplesHelpFormatter`): the example commands, each on its own line
    with its comment, then where the documentation is."""
    return "Examples:\n" + "\n".join(f"  {line}" for line in examples) + f"\n\nDocs: {docs}"


class OneLineParser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, `<prog>: error: <message>`, with exit code 2
    (the project's convention for bad input; the usage is in --help)."""

    def error(self, message: str):  # noqa: D102 (argparse API)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)
