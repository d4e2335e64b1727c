"""The high level's message channel: one-step delay, range-limited by true distance (numpy).

ConsMAC (`cefc_mj.nn.consmac`) computes each agent's message m_i^(t+1) during decision step t; its
neighbours read it during step t + 1, as M_nei^(t+1) (the paper's Fig. 2(b) and eq. (9)). The
channel enforces both rules of that exchange:

- **Delay.** `receive` opens a decision step and delivers what was `send`-t during the previous
  step, never what is sent during the current one. A step in which an agent sends nothing leaves
  nothing for that agent to deliver in the next (messages do not persist).
- **Range.** Agent i receives agent j's message when their *true* distance at the time of receipt
  is below `comm_range` (delta_obs = 3 m, the same strict "<" as the observation's neighbours).
  Radio range is physical, so sensing deviation does not enter it.

Received messages come sorted by that distance, nearest first (ties by index), in K = N - 1 slots
padded with zeros, with a mask, the distances, the senders' indices and a per-agent count. Every agent
also gets back its own previous message (`own`, the memory input m_i0^(t) of eq. (7)) regardless of
range. Pure numpy and batch-first [B, N, ...], so the particle and MuJoCo backends and a
multi-process deployment can all use it.

>>> ch = MessageChannel(n_envs=1, n_agents=3, message_dim=2)
>>> pos = np.array([[[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]]])
>>> ch.receive(pos).received.tolist()          # step 0: nothing has been sent yet
[[0, 0, 0]]
>>> ch.send(np.arange(6.0).reshape(1, 3, 2))
>>> inbox = ch.receive(pos)                     # step 1: step 0's messages arrive, in range only
>>> inbox.received.tolist(), inbox.sender[0, 0].tolist(), inbox.messages[0, 0, 0].tolist()
([[1, 1, 0]], [1, -1], [2.0, 3.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cefc_mj.errors import ConfigError


@dataclass(frozen=True)
class Inbox:
    """What every agent holds at the start of one decision step: [B, N, K, ...] with K = N - 1."""

    messages: np.ndarray
    """[B, N, K, D] float32: neighbours' messages sent during the previous step, nearest first; zeros
    in empty slots."""
    mask: np.ndarray
    """[B, N, K] bool: True where a slot holds a received message."""
    distance: np.ndarray
    """[B, N, K] float64: true distance (m) to each slot's sender at receipt; 0 in empty slots."""
    sender: np.ndarray
    """[B, N, K] int64: index of each slot's sender; -1 in empty slots."""
    received: np.ndarray
    """[B, N] int64: how many messages each agent received (the number of True slots)."""
    own: np.ndarray
    """[B, N, D] float32: each agent's own message from the previous step (zeros if it sent none),
    the memory input m_i0^(t) of eq. (7)."""


class MessageChannel:
    """Message exchange among the N agents of B envs; one `receive` then at most one `send` per step."""

    def __init__(self, n_envs: int, n_agents: int, message_dim: int, comm_range: float = 3.0):
        for name, value in (("n_envs", n_envs), ("n_agents", n_agents), ("message_dim", message_dim)):
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name}={value!r}: must be an integer >= 1")
        if not np.isfinite(comm_range) or comm_range <= 0:
            raise ConfigError(f"comm_range={comm_range!r}: must be a finite distance > 0 (m)")
        self.n_envs, self.n_agents, self.message_dim = int(n_envs), int(n_agents), int(message_dim)
        self.comm_range = float(comm_range)
        b, n, d = self.n_envs, self.n_agents, self.message_dim
        self._outbox = np.zeros((b, n, d), dtype=np.float32)  # sent during the current step
        self._outbox_sent = np.zeros((b, n), dtype=bool)
        self._delivering = np.zeros((b, n, d), dtype=np.float32)  # sent during the previous step
        self._delivering_sent = np.zeros((b, n), dtype=bool)
        self._sent_this_step = False

    @property
    def slots(self) -> int:
        """K = N - 1 neighbour slots per agent."""
        return self.n_agents - 1

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Forget every message of the masked envs (all by default): a new episode starts silent."""
        mask = np.ones(self.n_envs, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if mask.shape != (self.n_envs,):
            raise ConfigError(f"mask: expected shape ({self.n_envs},), got {mask.shape}")
        for array in (self._outbox, self._outbox_sent, self._delivering, self._delivering_sent):
            array[mask] = 0

    def send(self, messages: np.ndarray, sent: np.ndarray | None = None) -> None:
        """Queue each agent's message [B, N, D] for delivery during the next step.

        `sent` [B, N] bool marks which agents actually send (all by default); the others' rows are
        ignored. At most one call per step (after that step's `receive`).
        """
        messages = np.asarray(messages)
        if messages.shape != (self.n_envs, self.n_agents, self.message_dim):
            raise ConfigError(
                f"messages: expected shape ({self.n_envs}, {self.n_agents}, {self.message_dim}), got {messages.shape}"
            )
        if not np.isfinite(messages).all():
            raise ConfigError("messages: contain NaN or inf")
        sent = np.ones((self.n_envs, self.n_agents), dtype=bool) if sent is None else np.asarray(sent, dtype=bool)
        if sent.shape != (self.n_envs, self.n_agents):
            raise ConfigError(f"sent: expected shape ({self.n_envs}, {self.n_agents}), got {sent.shape}")
        if self._sent_this_step:
            raise ConfigError("send() called twice in one step; call receive() to start the next step first")
        self._outbox[:] = np.where(sent[..., None], messages, 0.0)
        self._outbox_sent[:] = sent
        self._sent_this_step = True

    def receive(self, positions: np.ndarray) -> Inbox:
        """Start a new decision step: deliver the previous step's messages to the agents in range.

        positions [B, N, 2]: the agents' true positions now (m).
        """
        pos = np.asarray(positions, dtype=np.float64)
        if pos.shape != (self.n_envs, self.n_agents, 2):
            raise ConfigError(f"positions: expected shape ({self.n_envs}, {self.n_agents}, 2), got {pos.shape}")
        if not np.isfinite(pos).all():
            raise ConfigError("positions: contain NaN or inf")
        # What was sent during the step that just ended becomes deliverable; the outbox starts empty.
        self._delivering, self._outbox = self._outbox, self._delivering
        self._delivering_sent, self._outbox_sent = self._outbox_sent, self._delivering_sent
        self._outbox[:] = 0.0
        self._outbox_sent[:] = False
        self._sent_this_step = False

        b, n, k = self.n_envs, self.n_agents, self.slots
        dist = np.linalg.norm(pos[:, None, :, :] - pos[:, :, None, :], axis=-1)  # [B, N(receiver), N(sender)]
        heard = (dist < self.comm_range) & self._delivering_sent[:, None, :] & ~np.eye(n, dtype=bool)
        # Nearest first; a stable sort keeps equal distances in index order; unheard senders go last.
        order = np.argsort(np.where(heard, dist, np.inf), axis=-1, kind="stable")[..., :k]
        mask = np.take_along_axis(heard, order, axis=-1)
        env = np.arange(b)[:, None, None]
        messages = np.where(mask[..., None], self._delivering[env, order], 0.0).astype(np.float32)
        return Inbox(
            messages=messages,
            mask=mask,
            distance=np.where(mask, np.take_along_axis(dist, order, axis=-1), 0.0),
            sender=np.where(mask, order, -1).astype(np.int64),
            received=mask.sum(axis=-1).astype(np.int64),
            own=np.where(self._delivering_sent[..., None], self._delivering, 0.0).astype(np.float32),
        )
