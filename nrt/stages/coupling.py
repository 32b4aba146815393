"""The optional coupling of the split stage 2 (``model.coupling``): carrying the photos'
gradient through the scattered light to the medium, off by default (docs/stage2.md,
"Coupling").

- ``unrolled_directions`` > 0: one source-iteration step of the scattered light unrolled
  with gradient per camera sample (``unrolled_samples`` strata), in the photos'
  in-scattering (:func:`nrt.losses.transport.unrolled_inscatter`);
- ``adjoint``: an adjoint SH grid (:class:`AdjointCoupling`) whose source is the photo
  loss's gradient to the scattered light's coefficients, trained one step per step toward
  its equation; the medium's sensitivity through it is backpropagated
  (:mod:`nrt.losses.adjoint`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch import nn

from nrt.errors import ConfigError
from nrt.losses.adjoint import adjoint_loss, medium_sensitivity
from nrt.losses.samplers import uniform_box_points
from nrt.losses.transport import uniform_samples
from nrt.modules.fields.sh_light_field import SHGrid, SHGridLightField
from nrt.modules.fields.voxel_medium import detached

COUPLING = {"unrolled_directions": 0, "unrolled_samples": 8, "adjoint": False,
            "adjoint_blend": 0.5}
"""``model.coupling``'s keys and defaults."""


def coupling_settings(coupling: Mapping | None) -> dict:
    """``model.coupling`` with the defaults of :data:`COUPLING`; unknown keys are refused."""
    unknown = set(coupling or {}) - set(COUPLING)
    if unknown:
        raise ConfigError(f"model.coupling has unknown keys {sorted(unknown)}; the keys are "
                          f"{list(COUPLING)} (conf/model/rte.yaml).")
    return {**COUPLING, **(coupling or {})}


class AdjointCoupling(nn.Module):
    """The adjoint of ``light`` (an :class:`SHGridLightField`) on the same grid: ``grid``
    (trained at the light's rate) and its ``source`` (a buffer), the photo gradient folded
    in with weight ``blend`` per step."""

    def __init__(self, light: nn.Module, blend: float):
        super().__init__()
        if not isinstance(light, SHGridLightField):
            raise ConfigError("model.coupling.adjoint=true needs model/light_field=sh_grid "
                              "(the adjoint is solved on the same SH grid).")
        self.blend = float(blend)
        self.grid = SHGridLightField(light.degree, light.resolution)
        self.register_buffer("source", torch.zeros_like(light.coefficients))
        self._leaf: torch.Tensor | None = None

    def photo_light(self, light: SHGridLightField) -> SHGrid:
        """``light`` read through a leaf of its coefficients, whose gradient (the photo
        loss's) :meth:`backward` takes."""
        self._leaf = light.coefficients.detach().requires_grad_(True)
        return SHGrid(self._leaf, light.uncollided, light.degree, light.bbox,
                      light.radiance_scale)

    def take_gradient(self) -> torch.Tensor | None:
        """The photo loss's gradient to the coefficients read this step (None without one)."""
        leaf, self._leaf = self._leaf, None
        return leaf.grad if leaf is not None else None

    def backward(self, light: SHGridLightField, medium, voxels: Callable[[], object],
                 grad: torch.Tensor, points: int, samples: int,
                 backward: Callable[[torch.Tensor], None]) -> torch.Tensor:
        """Fold ``grad`` into the source, backpropagate (``backward``) the adjoint's loss at
        ``points`` points with ``samples`` strata in ``medium`` (without gradient to it),
        then the sensitivity of the learned media (``voxels()``, composed anew) through the
        scattered light; returns the adjoint's loss (detached)."""
        bbox = light.bbox
        cell_volume = torch.prod(bbox[1] - bbox[0]) / light.resolution ** 3
        self.source.mul_(1 - self.blend).add_(self.blend * grad / cell_volume)
        q_scale = self.source.square().mean().sqrt().clamp_min(1e-30)
        one = self.grid.radiance_scale
        adjoint = SHGrid(self.grid.coefficients, self.grid.uncollided, light.degree, bbox, one)
        source = SHGrid(self.source / q_scale, self.grid.uncollided, light.degree, bbox, one)
        pts, dirs = uniform_samples(points, bbox)
        loss = adjoint_loss(adjoint, source, detached(medium), pts, dirs, samples)
        backward(loss)
        pts = uniform_box_points(points, bbox)
        backward(medium_sensitivity(adjoint, light.grid(), voxels(), pts, float(q_scale)))
        return loss.detach()
