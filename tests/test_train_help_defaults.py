"""Each `cefc-train` flag that sets a config field states the config's own default in its --help: the
default lives in the config dataclass, and the help text must not drift from it."""

import re

import pytest

from cefc_mj.cli.train import build_parser
from cefc_mj.train import adversary, highlevel
from cefc_mj.train.config import Budget

CASES = {
    "adversary": (adversary.AdversaryConfig, adversary.CLI_FIELDS, adversary.CLI_PPO_FIELDS),
    "highlevel": (highlevel.HighLevelConfig, highlevel.CLI_FIELDS, highlevel.CLI_PPO_FIELDS),
}
NOT_STATED = {"seed", "teams", "low_level", "adversary"}
"""Fields whose help describes the default in words (a policy name, a population) or has none."""


def _shown(value) -> str | float:
    return value if isinstance(value, str) else float(value)


@pytest.mark.parametrize("command", sorted(CASES))
def test_help_states_the_configs_defaults(command):
    config, fields, ppo_fields = CASES[command]
    defaults = config(budget=Budget(iterations=1))
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[command]
    checked = 0
    for action in sub._actions:
        if action.dest in NOT_STATED or action.help is None:
            continue
        if action.dest in fields:
            value = getattr(defaults, action.dest)
        elif action.dest in ppo_fields:
            value = getattr(defaults.ppo, action.dest)
        else:
            continue
        shown = re.search(r"\(default ([-+.\w/]+)", " ".join(action.help.split()))
        if shown is None or isinstance(value, (tuple, bool)) or value is None:
            continue
        text = shown.group(1)
        if "/" in text:  # a fraction such as 2/3
            numerator, denominator = text.split("/")
            assert float(numerator) / float(denominator) == pytest.approx(value), action.dest
        else:
            assert (text == value) if isinstance(value, str) else float(text) == pytest.approx(value), action.dest
        checked += 1
    assert checked >= 5, f"only {checked} flags of cefc-train {command} state a default"
