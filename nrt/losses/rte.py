"""Residual of the radiative transfer equation at collocation points in the box.

``r(x, w) = (w . grad_x) L + sigma_t L - sigma_s S``, ``S = S_mc + S_direct``: the Monte
Carlo in-scattering from the light field plus, for scenes with local emitters or a sun,
their first scattering (:mod:`nrt.physics.direct_light`). One travel direction ``w``, uniform on
the sphere, per point; the directional derivative is the SIREN's forward-mode tangent.
The squared residual is made unbiased with two independent in-scattering estimates
(:mod:`nrt.losses.unbiased`). Units: radiance_scale per unit length.
"""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule
from nrt.losses.samplers import collocation_points
from nrt.losses.unbiased import unbiased_square
from nrt.modules.fields.light_field import LightField
from nrt.modules.fields.medium import Medium
from nrt.modules.renderers.volume import DirectSource
from nrt.physics.inscatter import inscattered_radiance
from nrt.physics.phase import sample_uniform_sphere


def rte_residuals(light: LightField, medium: Medium, points: torch.Tensor, n_dirs: int,
                  detach_inscatter: bool = False, direct_source: DirectSource | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Two independent estimates ``(r_a, r_b)`` (N, 3) of the residual at ``points`` (N, 3)
    for random travel directions; ``r_a`` carries no graph, ``r_b`` does."""
    w = sample_uniform_sphere(torch.rand(points.shape[0], 2, dtype=points.dtype,
                                         device=points.device))
    props = medium(points)
    radiance, derivative = light.with_derivative(points, w)
    s_direct = direct_source(points, w, props) if direct_source is not None else 0.0

    def residual(s_mc: torch.Tensor) -> torch.Tensor:
        return (derivative + props.sigma_t * radiance - props.sigma_s * (s_mc + s_direct)
                ) / light.radiance_scale

    with torch.no_grad():
        g = None if props.g is None else props.g.detach()
        r_a = residual(inscattered_radiance(light, points, w, g, n_dirs))
    r_b = residual(inscattered_radiance(light, points, w, props.g, n_dirs,
                                        detach=detach_inscatter))
    return r_a, r_b


def rte_loss(light: LightField, medium: Medium, points: torch.Tensor, n_dirs: int,
             detach_inscatter: bool = False, direct_source: DirectSource | None = None
             ) -> torch.Tensor:
    """Unbiased mean squared RTE residual at ``points`` with ``n_dirs`` in-scattering
    directions per estimate."""
    return unbiased_square(*rte_residuals(light, medium, points, n_dirs, detach_inscatter,
                                          direct_source))


class RTEObjective(Objective):
    """``rte``: the residual at ``points`` collocation points, ``density_fraction`` of them
    drawn like the extinction (``context.density_sampler()``), with ``directions``
    in-scattering directions per estimate and the known lights' first scattering
    (``context.direct_source``); ``detach_inscatter``: no gradient into the light field
    through the in-scattered radiance."""

    name = "rte"

    def __init__(self, name: str, schedule: WeightSchedule, points: int,
                 density_fraction: float, directions: int, detach_inscatter: bool = False):
        super().__init__(name, schedule)
        self.points, self.density_fraction = int(points), float(density_fraction)
        self.directions, self.detach_inscatter = int(directions), bool(detach_inscatter)

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        [(medium, light)] = context.scenes
        pts = collocation_points(self.points, light.bbox, context.density_sampler(),
                                 self.density_fraction)
        return rte_loss(light, medium, pts, self.directions, self.detach_inscatter,
                        context.direct_source)
