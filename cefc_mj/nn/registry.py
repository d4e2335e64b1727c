"""The shipped policies' names, the aliases users type, and which policy each path flies by default.

    atm_c<c>_step1 / _step2 / _step3 / _safe / _nav     AT-M of group size c (paper Sec. IV-B) and this
                                                        project's navigation fine-tune, c = 3..8
    atm_c<c>_mujoco                                     AT-M-Nav fine-tuned in the MuJoCo world, where trained
    clm_c<c>                                            the CL-M baseline (Table III), where trained
    atm_student                                         one student for every c (the hierarchy's low level)

Every module that names a shipped low-level policy (training, evaluation, deployment, benchmarks,
the hierarchy) spells it through this module.
"""

from __future__ import annotations

from cefc_mj.errors import ConfigError

LOWLEVEL_KINDS = ("step1", "step2", "step3", "safe", "nav", "robust", "quad", "mujoco")
"""The suffixes of atm_c<c>_<kind>; robust and quad are trained on request only (none shipped)."""
STUDENT = "atm_student"
"""The distilled student: one policy for every group size."""

ALIASES = {"atm": "step3", "safe": "safe", "nav": "nav", "mujoco": "mujoco", "clm": "clm", "student": "student"}
"""What users type (`--policy`) -> the kind of policy flown for each c."""
WITHDRAWN = {
    "robust": "AT-M-Robust is withdrawn: the shipped one was a fine-tune of the first Step 3 generation on the "
    "old layouts; train one from today's Step 3 (docs/train_lowlevel.md) and give its file",
    "quad": "AT-M-Quad is withdrawn: the shipped one was a fine-tune of the first Step 3 generation on the old "
    "layouts; train one from today's Step 3 (docs/train_lowlevel.md) and give its file",
}
"""Aliases that once named shipped policies, with the line that says why they are gone."""

DEFAULT_LOWLEVEL = "nav"
"""The low level the evaluators (cefc-eval, the SITL-M agents, the benchmarks) fly without --policy:
AT-M-Nav of each c, the Step 3 policy fine-tuned with a larger navigation weight (docs/research/decisions.md)."""
HIERARCHY_LOWLEVEL = STUDENT
"""The low level under every high level (training and the game tables)."""
GAME_ADVERSARY = "adversary_ppo_nearest_group_intercept"
"""The adversary of the high level's game (training, Tables V and VII): the PPO adversary that imitates
the nearest-group-intercept rule; `adversary_ppo_nearest_group_member` and `adversary_ppo` (imitating
nearest_group_member and nearest_group_strike) were the previous generations' (docs/research/high_level.md)."""
DISTILL_TEACHER = "step3"
"""The teachers `cefc-train distill` imitates by default (the paper's: AT-M Step 3)."""


def lowlevel_name(formation: int, kind: str) -> str:
    """atm_c<c>_<kind> (kind in LOWLEVEL_KINDS)."""
    if kind not in LOWLEVEL_KINDS:
        raise ConfigError(f"low-level kind {kind!r}: must be one of {', '.join(LOWLEVEL_KINDS)}")
    return f"atm_c{formation}_{kind}"


def clm_name(formation: int) -> str:
    return f"clm_c{formation}"


FORMATION_PLACEHOLDER = "{c}"
"""In a --policy name or path, stands for the group size c of each episode."""


def policy_name_for(choice: str, formation: int) -> str:
    """The policy file name an alias stands for at group size c (anything else is a name or path, as
    given, with "{c}" replaced by c: `runs/mine/policies/atm_c{c}_mujoco.pt` names one file per c);
    ConfigError with the reason for a withdrawn alias."""
    if FORMATION_PLACEHOLDER in choice:
        return choice.replace(FORMATION_PLACEHOLDER, str(formation))
    if choice in WITHDRAWN:
        raise ConfigError(f"--policy {choice}: {WITHDRAWN[choice]}")
    kind = ALIASES.get(choice)
    if kind is None:
        return choice
    if kind == "student":
        return STUDENT
    return clm_name(formation) if kind == "clm" else lowlevel_name(formation, kind)
