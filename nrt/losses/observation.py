"""Observation constraint: a photo's pixel is the light field where its ray leaves the box
(:mod:`nrt.modules.renderers.exit`); rays that miss the box constrain nothing."""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective
from nrt.modules.fields.light_field import LightField
from nrt.modules.renderers.exit import exit_points


def observation_loss(light: LightField, origins: torch.Tensor, dirs: torch.Tensor,
                     pixels: torch.Tensor) -> torch.Tensor:
    """Mean squared error of ``L(x_exit, -v)`` against the photographed ``pixels`` over the
    rays that cross the box (0 when none does), in units of ``radiance_scale``."""
    x, hit = exit_points(light, origins, dirs)
    if not hit.any():
        return origins.new_zeros(())
    return torch.mean(((light(x, -dirs[hit]) - pixels[hit]) / light.radiance_scale) ** 2)


class ObservationObjective(Objective):
    """``obs``: the batch's photographed rays, but those that look into the sun (the
    illumination's ``sunless``): those see it through the medium, which the light field at
    the exit does not, and are left to the VRE."""

    name = "obs"

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        [(_, light)] = context.scenes
        keep = context.illumination.sunless(batch["dirs"])
        return observation_loss(light, batch["origins"][keep], batch["dirs"][keep],
                                batch["rgb"][keep])
