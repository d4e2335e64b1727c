"""The agent's onboard position estimator (docs/design.md §7, "Onboard position estimate").

A drone's position fix is noisy (the sensing deviation: p + delta, redrawn every decision step), but
its own motion is measured well: the agent's exact velocity, integrated at the simulator's rate, is
its displacement since the last decision (on a real drone IMU and optical-flow odometry feed PX4's
EKF the same way). The "fused" estimator is the textbook fusion of the two, a scalar Kalman filter
per agent and axis:

    predict  x- = x+ + displacement                      P- = P+ + Q
    correct  x+ = x- + K (fix - x-),  K = P- / (P- + R)  P+ = (1 - K) P-

seeded with the first fix of the episode (P = R). R and Q are design constants, not the true noise
(an agent does not know how noisy its fix is): R = FIX_STD^2, and Q = PREDICTION_STD^2 stands for
odometry drift. The steady-state gain is about sqrt(Q / R) = 0.04, so a white fix error averages out
over ~25 decision steps.

"raw" is the paper's memoryless agent: the estimate is the fix. Everything the agent perceives (its
anchor vector, the position it broadcasts, the origin of its LiDAR) is taken from the estimate.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

PositionEstimator = Literal["raw", "fused"]
POSITION_ESTIMATORS = ("raw", "fused")

FIX_STD = 0.5
"""Design std (m) of one position fix, per axis (R = FIX_STD^2)."""
PREDICTION_STD = 0.02
"""Design std (m) of one decision step's velocity-integration error, per axis (Q = PREDICTION_STD^2)."""


class FusedPositionEstimate:
    """Per-agent estimates [B, N, 2] of B envs x N agents, fused from fixes and own velocities."""

    def __init__(self, n_envs: int, n_agents: int):
        self.position = np.zeros((n_envs, n_agents, 2))
        self.variance = np.full((n_envs, n_agents), FIX_STD**2)

    def reset(self, mask: np.ndarray, fix: np.ndarray) -> None:
        """Start the masked envs' estimates at their first fix [B, N, 2]."""
        self.position[mask] = fix[mask]
        self.variance[mask] = FIX_STD**2

    def update(self, fix: np.ndarray, displacement: np.ndarray) -> np.ndarray:
        """One decision step later: predict with the agent's own displacement [B, N, 2], correct
        with the new fix [B, N, 2]; returns the estimates [B, N, 2] (the object's own array)."""
        self.position += displacement
        prior = self.variance + PREDICTION_STD**2
        gain = prior / (prior + FIX_STD**2)
        self.position += gain[..., None] * (fix - self.position)
        self.variance = (1.0 - gain) * prior
        return self.position
