"""Each `cefc-train` flag that sets a config field states the config's own default in its --help: the
default lives in the config dataclass, and the help text must not drift from it."""

import re

import pytest

from cefc_mj.cli import train_lowlevel
from cefc_mj.cli.train import build_parser
from cefc_mj.train import adversary, adversary_ddpg, benchmarl_config, highlevel_config
from cefc_mj.train.config import CLM_CURRICULUM, Budget, DistillConfig, LowLevelConfig, PPOConfig

BUDGET = Budget(iterations=1)
NOT_STATED = {"teams", "low_level", "adversary"}
"""Fields whose help describes the default in words (a policy name, a population) or has none."""


def _by_field(defaults, flag_of_field: dict[str, str]) -> dict[str, object]:
    """flag -> the default of the config field it sets, looked up in the `defaults` objects in turn."""
    found = {}
    for field, flag in flag_of_field.items():
        owner = next((d for d in defaults if hasattr(d, field)), None)
        if owner is not None and field not in NOT_STATED:
            found[flag] = getattr(owner, field)
    return found


def _by_dest(config, fields, ppo_fields):
    """For trainers whose flags' argparse dest is the config field (adversary, highlevel)."""

    def defaults(sub) -> dict[str, object]:
        d = config(budget=BUDGET)
        found = {}
        for action in sub._actions:
            if not action.option_strings or action.dest in NOT_STATED:
                continue
            if action.dest in fields:
                found[action.option_strings[-1]] = getattr(d, action.dest)
            elif action.dest in ppo_fields:
                found[action.option_strings[-1]] = getattr(d.ppo, action.dest)
        return found

    return defaults


def _lowlevel(sub):
    cfg = LowLevelConfig(formation=3, step=1, budget=BUDGET)
    return _by_field((cfg, cfg.ppo), train_lowlevel.FLAG_OF_FIELD)


def _clm(sub):  # the curriculum cefc-train clm trains without --curriculum
    cfg = LowLevelConfig(formation=3, step=1, budget=Budget(iterations=len(CLM_CURRICULUM)), curriculum=CLM_CURRICULUM)
    return _by_field((cfg, cfg.ppo), train_lowlevel.FLAG_OF_FIELD)


def _distill(sub):
    return _by_field((DistillConfig(budget=BUDGET),), train_lowlevel.FLAG_OF_FIELD)


def _pipeline(sub):  # PPO flags, then the distillation's
    return _by_field((PPOConfig(), DistillConfig(budget=BUDGET)), train_lowlevel.FLAG_OF_FIELD)


def _ddpg(sub):
    return _by_field((adversary_ddpg.DDPGAdversaryConfig(budget=BUDGET),), adversary_ddpg.FLAG_OF_FIELD)


def _benchmarl(sub):
    return _by_field((benchmarl_config.BenchMARLConfig(),), benchmarl_config.FLAG_OF_FIELD)


def _formation_benchmarl(sub):
    return _by_field((benchmarl_config.FormationBenchMARLConfig(),), benchmarl_config.FORMATION_FLAG_OF_FIELD)


CASES = {
    # command: (flag -> the config's default, of the subcommand's parser; fewest flags checked)
    "adversary": (_by_dest(adversary.AdversaryConfig, adversary.CLI_FIELDS, adversary.CLI_PPO_FIELDS), 5),
    "highlevel": (
        _by_dest(highlevel_config.HighLevelConfig, highlevel_config.CLI_FIELDS, highlevel_config.CLI_PPO_FIELDS),
        5,
    ),
    "adversary-ddpg": (_ddpg, 5),
    "lowlevel": (_lowlevel, 5),
    "clm": (_clm, 5),
    "distill": (_distill, 3),
    "lowlevel-all": (_pipeline, 5),
    "highlevel-benchmarl": (_benchmarl, 5),
    "formation-benchmarl": (_formation_benchmarl, 5),
}


def _matches(text: str, value) -> bool:
    if isinstance(value, tuple):  # 3,4,5,6,7,8 or 0,0.01,0.02,0.03
        shown = text.split(",")
        return len(shown) == len(value) and all(float(s) == pytest.approx(v) for s, v in zip(shown, value))
    if isinstance(value, str):
        return text == value
    if "/" in text:  # a fraction such as 2/3
        numerator, denominator = text.split("/")
        return float(numerator) / float(denominator) == pytest.approx(value)
    return float(text) == pytest.approx(value)


def test_every_subcommand_is_checked():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(sub.choices) == set(CASES)


@pytest.mark.parametrize("command", sorted(CASES))
def test_help_states_the_configs_defaults(command):
    defaults_of, fewest = CASES[command]
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[command]
    defaults = defaults_of(sub)
    checked = 0
    for action in sub._actions:
        flag = action.option_strings[-1] if action.option_strings else None
        if flag not in defaults or action.help is None:
            continue
        value = defaults[flag]
        shown = re.search(r"\(default ([^\s)]+)", " ".join(action.help.split()))
        if shown is None or isinstance(value, bool) or value is None:
            continue
        text = shown.group(1).rstrip(",;")
        assert _matches(text, value), f"{flag}: help says (default {text}), the config's is {value!r}"
        if action.default is not None:  # a flag that passes its default on: the config's own
            assert action.default == value, flag
        checked += 1
    assert checked >= fewest, f"only {checked} flags of cefc-train {command} state a default"
