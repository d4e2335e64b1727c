"""The agent's push observer: an onboard estimate of the acceleration it feels but did not command.

The paper's low level is memoryless: it sees where it is and how fast it moves, not what pushes it.
Through PX4's acceleration interface (setpoint straight to tilt, no integral) a steady wind then
moves a drone at the speed at which the policy's own velocity loop balances the push. A disturbance
observer supplies the memory a memoryless policy lacks: with v the agent's own velocity (measured
well, as the position estimator assumes: IMU and odometry through PX4's EKF) and u the setpoint it
sent over the last decision step of length dt,

    raw  = (v_t - v_{t-1}) / dt - u_{t-1}              what moved the drone beyond its own setpoint
    d_t  = d_{t-1} + (dt / tau) (raw - d_{t-1})         a first-order low-pass, time constant tau

and the setpoint it sends is clip(command - d_t, +-accel_max): the policy's command with the push
cancelled, inside the same action bound. In calm air and in the particle world d stays near 0 (up to
the attitude's response lag and the particle world's speed cap); in steady wind it settles at the
push within a few tau. This is an integral action of the agent's, not PX4's (PX4's acceleration
interface has none): `TaskConfig.push_observer_s` > 0 switches it on, 0 is the paper's agent.
"""

from __future__ import annotations

import numpy as np

MAX_PUSH_OBSERVER_S = 10.0
"""Longest time constant (s) the trainers and evaluators take: a slower observer would lag a wind that
changes every 0.5 s by tens of seconds."""


class PushObserver:
    """Per-agent push estimates [B, N, 2] (m/s^2) of B envs x N agents."""

    def __init__(self, n_envs: int, n_agents: int, time_constant: float, dt: float, accel_max: float):
        self.gain = min(1.0, dt / time_constant)
        self.dt = dt
        self.accel_max = accel_max
        self.push = np.zeros((n_envs, n_agents, 2))
        self._velocity = np.zeros((n_envs, n_agents, 2))
        self._sent = np.zeros((n_envs, n_agents, 2))

    def reset(self, mask: np.ndarray, velocity: np.ndarray) -> None:
        """Start the masked envs' observers: no push known yet, the current velocity [B, N, 2] as the last."""
        self.push[mask] = 0.0
        self._velocity[mask] = velocity[mask]
        self._sent[mask] = 0.0

    def setpoint(self, command: np.ndarray) -> np.ndarray:
        """The setpoint sent for a command [B, N, 2]: the push estimate cancelled, clipped to the bound."""
        self._sent = np.clip(command - self.push, -self.accel_max, self.accel_max)
        return self._sent

    def update(self, velocity: np.ndarray) -> np.ndarray:
        """One decision step later, with the agents' velocities [B, N, 2]; returns the estimates."""
        raw = (velocity - self._velocity) / self.dt - self._sent
        self.push += self.gain * (raw - self.push)
        self._velocity = velocity.copy()
        return self.push
