"""Inflow boundary condition: ``L(x, w) = E(-w)`` on the box faces where ``w . n < 0``."""

from __future__ import annotations

import torch

from nrt.losses.objective import Objective, Scenes
from nrt.losses.samplers import boundary_samples
from nrt.modules.fields.light_field import LightField


def boundary_loss(light: LightField, points: torch.Tensor, dirs: torch.Tensor,
                  inflow: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of ``L(points, dirs)`` and the environment's inflowing
    radiance ``inflow = E(-dirs)`` (all (N, 3)), in units of ``radiance_scale``."""
    s = light.radiance_scale
    return torch.mean((torch.log1p(light(points, dirs) / s) - torch.log1p(inflow / s)) ** 2)


class BoundaryObjective(Objective):
    """``bc``: the inflow condition at ``samples.boundary_points`` points on the box faces,
    ``env_fraction`` of their directions drawn like the sun-less environment
    (``stage.sky.sampler``), against the sun-less sky ``stage.sky.rest``."""

    name = "bc"

    def loss(self, stage, batch: dict, scenes: Scenes) -> torch.Tensor:
        [(_, light)], s = scenes, stage.hparams.samples
        pts, w = boundary_samples(int(s["boundary_points"]), light.bbox, stage.sky.sampler,
                                  float(s["env_fraction"]))
        return boundary_loss(light, pts, w, stage.sky.rest.lookup(-w).to(pts.dtype))
