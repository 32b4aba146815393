"""Observation constraint: a photo's pixel is the light field where its ray leaves the box
(:mod:`nrt.modules.renderers.exit`); rays that miss the box constrain nothing."""

from __future__ import annotations

import torch

from nrt.losses.objective import Objective, Scenes
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
    """``obs``: the batch's photographed rays, but those that look into the sun
    (``stage.sunless``): those see it through the medium, which the light field at the exit
    does not, and are left to the VRE."""

    name = "obs"

    def loss(self, stage, batch: dict, scenes: Scenes) -> torch.Tensor:
        [(_, light)] = scenes
        keep = stage.sunless(batch["dirs"])
        return observation_loss(light, batch["origins"][keep], batch["dirs"][keep],
                                batch["rgb"][keep])
