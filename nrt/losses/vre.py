"""The volume rendering objective: photos against the VRE's render of their rays
(:func:`~nrt.modules.renderers.volume.vre_render`), made unbiased in the in-scattering
directions."""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule
from nrt.losses.unbiased import unbiased_square
from nrt.modules.fields.light_field import LightField
from nrt.modules.fields.medium import Medium
from nrt.modules.renderers.volume import DirectSource, vre_render
from nrt.physics.volume import ray_box_intersect


def vre_loss(light: LightField, medium: Medium, origins: torch.Tensor, dirs: torch.Tensor,
             pixels: torch.Tensor, background: torch.Tensor, n_samples: int, n_dirs: int,
             detach_inscatter: bool = False, direct_source: DirectSource | None = None
             ) -> torch.Tensor:
    """Mean squared error (units of radiance_scale) of the rendered against the
    photographed ``pixels`` over the rays that cross the box (0 when none does), made
    unbiased with respect to the in-scattering directions only.

    Two estimates with independent directions and shared jittered positions ``t`` enter
    :func:`~nrt.losses.unbiased.unbiased_square`, so the value is unbiased for
    ``E_t[(E[I | t] - P)^2] = (E[I] - P)^2 + Var_t(E[I | t])`` and the gradient for its
    gradient: the directions' variance is gone, the positions' is not (nor a covariance of
    the positions in the gradient). Measured on a medium varying 40x across the box
    (tests/modules/renderers/test_vre.py): the positions' variance is 7% of one render's
    variance (the bias of a plain square) with 1 stratum per ray, 4% with 4, 0.7% with 16 and
    0.3% (within noise) with 32; the presets use 16-32. Independent positions too (the medium
    and the lights' first scattering evaluated twice) made this objective 1.3-1.4x (cpu
    preset) and 1.9-2.1x (tiny) slower, measured on 2 shared cores. ``E[I]`` itself is the
    alpha-composited quadrature of the VRE, whose error shrinks with ``n_samples``."""
    _, _, hit = ray_box_intersect(origins, dirs, medium.bbox)
    if not hit.any():
        return origins.new_zeros(())
    i_a, i_b = vre_render(light, medium, origins[hit], dirs[hit], background[hit], n_samples,
                          n_dirs, True, detach_inscatter, direct_source, estimates=2)
    return unbiased_square((i_a - pixels[hit]) / light.radiance_scale,
                           (i_b - pixels[hit]) / light.radiance_scale)


class VREObjective(Objective):
    """``vre``: the first ``rays`` rays of the batch rendered with ``samples`` strata and
    ``directions`` in-scattering directions per estimate, with the known lights' first
    scattering (``context.direct_source``); ``detach_inscatter`` as :class:`RTEObjective`'s."""

    name = "vre"

    def __init__(self, name: str, schedule: WeightSchedule, rays: int, samples: int,
                 directions: int, detach_inscatter: bool = False):
        super().__init__(name, schedule)
        self.rays, self.samples, self.directions = int(rays), int(samples), int(directions)
        self.detach_inscatter = bool(detach_inscatter)

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        [(medium, light)], n = context.scenes, self.rays
        return vre_loss(light, medium, batch["origins"][:n], batch["dirs"][:n],
                        batch["rgb"][:n], batch["background"][:n], self.samples,
                        self.directions, self.detach_inscatter, context.direct_source)
