"""Every console script's --help, and every `cefc-train` subcommand's, ends with examples and a docs
pointer: each example parses with the script's own parser, and every docs page a help text names is
in the checkout."""

from __future__ import annotations

import importlib
import re
import shlex
import tomllib

import pytest

from cefc_mj import paths

SCRIPTS = tomllib.loads((paths.PROJECT_ROOT / "pyproject.toml").read_text())["project"]["scripts"]
DOCS_PAGE = re.compile(r"\bdocs/[\w/.-]+?\.md\b")


def _module(script: str):
    return importlib.import_module(SCRIPTS[script].split(":")[0])


def _help(script: str, *subcommand: str) -> str:
    parser = _module(script).build_parser()
    if subcommand:
        parser = _subparsers(parser)[subcommand[0]]
    return parser.format_help()


def _subparsers(parser) -> dict:
    (action,) = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    return action.choices


def _examples(text: str, command: str) -> list[str]:
    """The example command lines of a help text (indented, starting with `command`), comments cut."""
    lines = [line.strip() for line in text.splitlines() if line.startswith("  ") and line.strip().startswith(command)]
    return [line.split("  #")[0].strip() for line in lines]


HELPS = [(script,) for script in SCRIPTS] + [
    ("cefc-train", name) for name in _subparsers(_module("cefc-train").build_parser())
]


def test_every_console_script_and_train_subcommand_is_covered():
    assert set(SCRIPTS) == {"cefc-eval", "cefc-train", "cefc-agent", "cefc-mavlink", "cefc-view"}
    assert len(HELPS) >= 5 + 9  # the five scripts and cefc-train's subcommands (9 when this was written)


@pytest.mark.parametrize("which", HELPS, ids=[" ".join(h) for h in HELPS])
def test_help_has_examples_that_parse_and_a_docs_pointer(which):
    script, *subcommand = which
    text = _help(script, *subcommand)
    command = " ".join(which)
    examples = _examples(text.split("Examples:", 1)[-1], command)
    assert "Examples:" in text and examples, f"{command} --help has no example"
    for example in examples:
        argv = shlex.split(example)[1:]
        _module(script).build_parser().parse_args(argv)  # exits 2, failing the test, on a bad example
    assert re.search(r"^Docs: .*docs/\w+\.md", text, re.M), f"{command} --help names no docs page"


def test_help_names_only_docs_pages_that_exist():
    missing = {}
    for which in HELPS:
        for page in DOCS_PAGE.findall(" ".join(_help(*which).split())):
            if not (paths.PROJECT_ROOT / page).is_file():
                missing.setdefault(page, []).append(" ".join(which))
    assert not missing, f"--help texts name docs pages that are not in the checkout: {missing}"


def test_train_describes_every_kind_of_subcommand():
    """cefc-train trains the low level, the high level and the adversaries, and says so."""
    description = " ".join(_help("cefc-train").split("positional arguments")[0].split())
    assert "the low level" in description and "the high level" in description and "adversaries" in description


def test_view_says_it_needs_a_display_and_how_to_render_offscreen():
    text = " ".join(_help("cefc-view").split())
    assert "it needs a display (DISPLAY or WAYLAND_DISPLAY)" in text
    assert "MUJOCO_GL=egl" in text and "MUJOCO_GL=osmesa" in text


def test_eval_labels_the_main_job_as_a_combination_the_paper_does_not_fly():
    text = _help("cefc-eval")
    first = text.split("Examples:", 1)[1].split("\n  cefc-eval --protocol", 1)[0]
    assert "cefc-eval --wind 8 --deviation 0.5" in first and "the main job" in first
    assert "Table VIII" not in first and "the paper does not fly" in " ".join(first.replace("#", " ").split())
