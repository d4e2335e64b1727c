"""Sensing deviation (DESIGN §7): agent i perceives from p_i + delta_i.

|delta_i| ~ |Normal(d, d/4)| in a uniformly random direction, redrawn every decision step. The
physics and the metrics keep using the true states.
"""

from __future__ import annotations

import numpy as np


def sample_deviation(rng: np.random.Generator, deviation: float, shape: tuple[int, int]) -> np.ndarray:
    """Deviation vectors [B, N, 2] for a mean magnitude `deviation` (m); zeros when it is 0."""
    if deviation == 0:
        return np.zeros((*shape, 2))
    magnitude = np.abs(rng.normal(deviation, deviation / 4.0, size=shape))
    angle = rng.uniform(0.0, 2.0 * np.pi, size=shape)
    return magnitude[..., None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
