"""SIREN: a sine-activated MLP (Sitzmann et al. 2020) with an analytic forward-mode tangent.

``y = W_L sin(W_{L-1} ... sin(W_0 x + b_0) ...) + b_L``. The frequency ``omega_0`` is folded
into the weights and biases (``sin(omega_0 (W x + b))`` becomes ``sin(W' x + b')``), which
is the same function and initialisation at no cost per evaluation. Initialisation follows
Sitzmann: first layer ``W ~ U(-1/n, 1/n)``, later layers ``U(-sqrt(6/n)/omega_0, +)``,
before folding. :meth:`Siren.forward_with_tangent` returns ``y`` and the directional
derivative ``J(x) v`` in one pass (about twice a forward, far cheaper than a gradient).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn
from torch.profiler import record_function

from nrt.errors import ConfigError


class Siren(nn.Module):
    """``in_dim -> out_dim`` through ``layers`` sine layers of width ``hidden``."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 128, layers: int = 3,
                 omega_0: float = 30.0, omega_hidden: float = 30.0):
        super().__init__()
        if layers < 1 or hidden < 1:
            raise ConfigError(f"a SIREN needs layers >= 1 and hidden >= 1, got {layers}, "
                              f"{hidden}.")
        dims = [in_dim] + [hidden] * layers
        self.linears = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:],
                                                                       strict=True))
        self.out = nn.Linear(hidden, out_dim)
        with torch.no_grad():
            for i, lin in enumerate(self.linears):
                omega = omega_0 if i == 0 else omega_hidden
                bound = 1.0 / lin.in_features if i == 0 else math.sqrt(6 / lin.in_features) / omega
                lin.weight.uniform_(-bound, bound).mul_(omega)
                lin.bias.mul_(omega)  # default U(-1/sqrt(n), 1/sqrt(n)), then folded
            bound = math.sqrt(6 / hidden) / omega_hidden
            self.out.weight.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with record_function("nrt/mlp"):  # a profiler scope (benchmarks.profile_step)
            for lin in self.linears:
                x = torch.sin(lin(x))
            return self.out(x)

    def forward_with_tangent(self, x: torch.Tensor, v: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(y(x), J(x) v)`` for inputs ``x`` and input tangents ``v`` of the same shape."""
        with record_function("nrt/mlp"):
            for lin in self.linears:
                z = lin(x)
                v = torch.cos(z) * F.linear(v, lin.weight)
                x = torch.sin(z)
            return self.out(x), F.linear(v, self.out.weight)
