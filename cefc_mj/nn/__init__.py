"""Network modules: the AT-M low-level actor (teachers and distilled student), the centralized
critic, and policy files with the evaluators' loading API (`load_policy`)."""

from cefc_mj.nn.atm import ATMActor, ATMConfig, Critic, merge_step3
from cefc_mj.nn.policy_io import Policy, load_actor, load_policy, resolve_policy_path, save_policy

__all__ = [
    "ATMActor",
    "ATMConfig",
    "Critic",
    "merge_step3",
    "Policy",
    "load_actor",
    "load_policy",
    "resolve_policy_path",
    "save_policy",
]
