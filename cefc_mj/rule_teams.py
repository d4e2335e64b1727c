"""Rule-driven UAV teams: scripted high levels that pick each agent's anchor from the game's true
state. They join the learned teams in the PPO adversary's training population (train/adversary.py),
so the adversary meets behaviours no learned team shows; they are not deployable agents.

- "rule-urgent": every agent flies to the most urgent target (one group, straight to the work).
- "rule-split": the first half of the agents to one target, the rest to the other (two groups); a
  covered target (urgency 0) sends its half to the other.
- "rule-evade": each agent flies to the uncovered target farthest from the adversary, or, with none
  left, to the anchor farthest from it.

A team plays like a `HighLevelPolicy` without communication (`comm` None, `decide(obs, inbox)`), so
`game_protocol.play_highlevel` plays it unchanged.
"""

from __future__ import annotations

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.hierarchy import HierarchicalCEFCEnv
from cefc_mj.task.config import RULE_TEAMS


class RuleTeam:
    """One rule of RULE_TEAMS, bound to the game whose state it reads."""

    comm = None
    message_dim = 0
    variant = "rule"

    def __init__(self, name: str, game: HierarchicalCEFCEnv):
        if name not in RULE_TEAMS:
            raise ConfigError(f"rule team {name!r}: must be one of {', '.join(RULE_TEAMS)}")
        self.name, self.game = name, game

    def _anchor_of(self, points: np.ndarray) -> np.ndarray:
        """Index [...] of the anchor nearest each point [..., 2]."""
        return np.linalg.norm(points[..., None, :] - self.game.grid, axis=-1).argmin(axis=-1)

    def decide(self, obs: np.ndarray, inbox=None, deterministic: bool = True, generator=None):
        """(anchor index [B, N], None) for the game's current state; obs and inbox are not read."""
        env = self.game.env
        targets, urgency = env.targets, env.urgency  # [B, J, 2], [B, J]
        b, n = env.n_envs, env.n_agents
        rows = np.arange(b)
        if self.name == "rule-urgent":
            goal = targets[rows, urgency.argmax(axis=-1)]  # [B, 2]
            return np.repeat(self._anchor_of(goal)[:, None], n, axis=1), None
        if self.name == "rule-split":
            j = targets.shape[1]
            choice = np.broadcast_to((np.arange(n) >= n // 2).astype(int) % j, (b, n))  # [B, N] target index
            if j == 2:  # a covered target's half goes to the other
                choice = np.where(np.take_along_axis(urgency > 0, choice, axis=1), choice, 1 - choice)
            return self._anchor_of(np.take_along_axis(targets, choice[..., None], axis=1)), None
        adversary = env.world.adversary_pos  # rule-evade
        away = np.linalg.norm(targets - adversary[:, None], axis=-1)  # [B, J]
        best = np.where(urgency > 0, away, -np.inf).argmax(axis=-1)
        goal = targets[rows, best]
        fallback = self.game.grid[np.linalg.norm(self.game.grid[None] - adversary[:, None], axis=-1).argmax(axis=-1)]
        goal = np.where((urgency > 0).any(axis=-1)[:, None], goal, fallback)
        return np.repeat(self._anchor_of(goal)[:, None], n, axis=1), None
