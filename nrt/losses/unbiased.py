"""Unbiased squared Monte Carlo residuals (Azinovic et al. 2019).

For a residual ``r`` estimated by Monte Carlo, ``mean(r_hat^2)`` is biased by the
estimator's variance, and so is its gradient. With two independent estimates ``r_a``,
``r_b`` of the same residual, ``r_a r_b`` is unbiased for ``r^2`` and ``2 r_a d r_b``
unbiased for its gradient ``2 r dr``: the value uses one sample set and the gradient the
other, and only ``r_b`` needs a graph.
"""

from __future__ import annotations

import torch


def unbiased_square(r_value: torch.Tensor, r_grad: torch.Tensor) -> torch.Tensor:
    """Mean over all entries of the surrogate with value ``r_a r_b`` and gradient
    ``2 r_a d r_b``; ``r_value`` (= r_a) is treated as a constant."""
    a, b = r_value.detach(), r_grad
    return (a * b.detach() + 2 * a * (b - b.detach())).mean()
