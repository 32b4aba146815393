"""The light field ``L_theta(x, w) -> RGB >= 0``: radiance at ``x`` travelling along ``w``.

A SIREN on ``(x_unit, w)``, ``x_unit`` the point mapped from the medium box to [-1, 1]^3.
Radiance is ``radiance_scale * exp(y)``: the network works in log units of the scene's
typical environment radiance (set once from the training environment), so a sun 100-1e4
times brighter than the sky is a few units of ``y`` away, not a weight the SIREN must grow
by orders of magnitude. ``y`` is clamped at :data:`LOG_RADIANCE_MAX` so exp never
overflows. :meth:`LightField.with_derivative` adds the directional
derivative ``(w . grad_x) L`` by forward mode (the SIREN's analytic tangent).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.profiler import record_function

from nrt.modules.encodings.siren import Siren

LOG_RADIANCE_MAX = 30.0
"""Largest ``y``: radiance up to ``e^30 ~ 1e13`` times the scale, never ``inf``."""


class LightField(nn.Module):
    """Radiance (..., 3) at world points (..., 3) in unit travel directions (..., 3)."""

    def __init__(self, hidden: int = 128, layers: int = 3, omega_0: float = 30.0,
                 omega_hidden: float = 30.0):
        super().__init__()
        self.net = Siren(6, 3, hidden, layers, omega_0, omega_hidden)
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        self.register_buffer("radiance_scale", torch.tensor(1.0))

    def _inputs(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        x, w = torch.broadcast_tensors(x, w)
        unit = (x - self.bbox[0]) / (self.bbox[1] - self.bbox[0]) * 2 - 1
        return torch.cat((unit, w), -1)

    def forward(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        with record_function("nrt/light_field"):  # a profiler scope (benchmarks.profile_step)
            return self.radiance_scale * torch.exp(self.net(self._inputs(x, w)).clamp(
                max=LOG_RADIANCE_MAX))

    def with_derivative(self, x: torch.Tensor, w: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """``L(x, w)`` and ``(w . grad_x) L(x, w)``, both (..., 3), in one forward-mode pass."""
        with record_function("nrt/light_field"):
            inp = self._inputs(x, w)
            dx = w.expand_as(inp[..., :3]) * (2 / (self.bbox[1] - self.bbox[0]))
            y, dy = self.net.forward_with_tangent(inp, torch.cat((dx, torch.zeros_like(dx)), -1))
            radiance = self.radiance_scale * torch.exp(y.clamp(max=LOG_RADIANCE_MAX))
            return radiance, torch.where(y < LOG_RADIANCE_MAX, radiance * dy,
                                         torch.zeros_like(dy))
