"""The light field seen by a camera: a photo's pixel is the light field where its ray
leaves the box.

Radiance is constant along a ray in vacuum, so ``I = L(o, -v) = L(x_exit, -v)`` with
``x_exit = o + t_near v`` the point where light travelling toward the camera leaves B
(the camera ray's entry point). Rays that miss B see ``E(v)``.
"""

from __future__ import annotations

import torch

from nrt.modules.fields.light_field import LightField
from nrt.physics.volume import ray_box_intersect


def exit_points(light: LightField, origins: torch.Tensor, dirs: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The exit points ``x_exit`` (H, 3) of the rays that cross the box, and ``hit`` (R,)."""
    t_near, _, hit = ray_box_intersect(origins, dirs, light.bbox)
    return origins[hit] + t_near[hit, None] * dirs[hit], hit


def exit_radiance(light: LightField, origins: torch.Tensor, dirs: torch.Tensor,
                  background: torch.Tensor) -> torch.Tensor:
    """Predicted pixels ``L(o, -v)`` (R, 3): the light field at the exit point for rays
    through the box, the background ``E(v)`` for the others."""
    x, hit = exit_points(light, origins, dirs)
    out = background.clone()
    out[hit] = light(x, -dirs[hit]).to(out.dtype)
    return out
