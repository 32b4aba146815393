"""Inflow boundary condition: ``L(x, w) = E(-w)`` on the box faces where ``w . n < 0``."""

from __future__ import annotations

import torch

from nrt.modules.fields.light_field import LightField


def boundary_loss(light: LightField, points: torch.Tensor, dirs: torch.Tensor,
                  inflow: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of ``L(points, dirs)`` and the environment's inflowing
    radiance ``inflow = E(-dirs)`` (all (N, 3)), in units of ``radiance_scale``."""
    s = light.radiance_scale
    return torch.mean((torch.log1p(light(points, dirs) / s) - torch.log1p(inflow / s)) ** 2)
