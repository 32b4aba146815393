"""Inflow boundary condition: ``L(x, w) = E(-w)`` on the box faces where ``w . n < 0``."""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule
from nrt.losses.samplers import boundary_samples
from nrt.modules.fields.light_field import LightField


def boundary_loss(light: LightField, points: torch.Tensor, dirs: torch.Tensor,
                  inflow: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of ``L(points, dirs)`` and the environment's inflowing
    radiance ``inflow = E(-dirs)`` (all (N, 3)), in units of ``radiance_scale``."""
    s = light.radiance_scale
    return torch.mean((torch.log1p(light(points, dirs) / s) - torch.log1p(inflow / s)) ** 2)


class BoundaryObjective(Objective):
    """``bc``: the inflow condition at ``points`` points on the box faces, ``env_fraction``
    of their directions drawn like the sun-less environment (the illumination's
    ``sampler``), against the sun-less sky (its ``rest``)."""

    name = "bc"

    def __init__(self, name: str, schedule: WeightSchedule, points: int, env_fraction: float):
        super().__init__(name, schedule)
        self.points, self.env_fraction = int(points), float(env_fraction)

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        [(_, light)], sky = context.scenes, context.illumination
        pts, w = boundary_samples(self.points, light.bbox, sky.sampler, self.env_fraction)
        return boundary_loss(light, pts, w, sky.rest.lookup(-w).to(pts.dtype))
