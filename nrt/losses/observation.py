"""Observation constraint: a photo's pixel is the light field where its ray leaves the box.

Radiance is constant along a ray in vacuum, so ``I = L(o, -v) = L(x_exit, -v)`` with
``x_exit = o + t_near v`` the point where light travelling toward the camera leaves B
(the camera ray's entry point). Rays that miss B see ``E(v)`` and constrain nothing.
"""

from __future__ import annotations

import torch

from nrt.modules.light_field import LightField
from nrt.physics.volume import ray_box_intersect


def _exit_points(light: LightField, origins: torch.Tensor, dirs: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    t_near, _, hit = ray_box_intersect(origins, dirs, light.bbox)
    return origins[hit] + t_near[hit, None] * dirs[hit], hit


def exit_radiance(light: LightField, origins: torch.Tensor, dirs: torch.Tensor,
                  background: torch.Tensor) -> torch.Tensor:
    """Predicted pixels ``L(o, -v)`` (R, 3): the light field at the exit point for rays
    through the box, the background ``E(v)`` for the others."""
    x, hit = _exit_points(light, origins, dirs)
    out = background.clone()
    out[hit] = light(x, -dirs[hit]).to(out.dtype)
    return out


def observation_loss(light: LightField, origins: torch.Tensor, dirs: torch.Tensor,
                     pixels: torch.Tensor) -> torch.Tensor:
    """Mean squared error of ``L(x_exit, -v)`` against the photographed ``pixels`` over the
    rays that cross the box (0 when none does), in units of ``radiance_scale``."""
    x, hit = _exit_points(light, origins, dirs)
    if not hit.any():
        return origins.new_zeros(())
    return torch.mean(((light(x, -dirs[hit]) - pixels[hit]) / light.radiance_scale) ** 2)
