"""The CHOMP collision cost used by iSDF's evaluation (protocol.md).

    c(d) = -d + e/2          for d <= 0
         = (d - e)^2 / (2e)  for 0 < d <= e
         = 0                 for d > e
"""

from __future__ import annotations

import numpy as np


def chomp_cost(d, epsilon: float):
    """CHOMP cost of signed distances ``d`` (numpy array or torch tensor), epsilon > 0."""
    if epsilon <= 0:
        raise ValueError(f"epsilon must be positive, got {epsilon}")
    if isinstance(d, np.ndarray) or np.isscalar(d):
        d = np.asarray(d, dtype=np.float64)
        return np.where(d <= 0, -d + epsilon / 2, np.where(d <= epsilon, (d - epsilon) ** 2 / (2 * epsilon), 0.0))
    import torch

    return torch.where(
        d <= 0,
        -d + epsilon / 2,
        torch.where(d <= epsilon, (d - epsilon) ** 2 / (2 * epsilon), torch.zeros_like(d)),
    )
