"""Sensing deviation (docs/design.md §7): agent i perceives from p_i + delta_i.

|delta_i| ~ |Normal(d, d/4)| in a uniformly random direction, redrawn every decision step. The
physics and the metrics keep using the true states.
"""

from __future__ import annotations

import numpy as np


def sample_deviation(rng: np.random.Generator, deviation: float | np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Deviation vectors [B, N, 2] for a mean magnitude `deviation` (m), a number or one per env [B];
    zeros (and no random draw) when it is 0 everywhere."""
    deviation = np.asarray(deviation, dtype=np.float64)
    if not deviation.any():
        return np.zeros((*shape, 2))
    if deviation.ndim == 1:
        deviation = deviation[:, None]
    magnitude = np.abs(rng.normal(deviation, deviation / 4.0, size=shape))
    angle = rng.uniform(0.0, 2.0 * np.pi, size=shape)
    return magnitude[..., None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
