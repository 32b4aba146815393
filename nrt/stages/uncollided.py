"""The uncollided light's cache of the split stage 2 (:class:`UncollidedCache`): the SH
projection of the light that reaches a point without scattering (the sun-less sky by MIS
shadow rays, the suns and emitters by shadow rays), at a scattered-light field's cache
points, refreshed from the current medium every ``samples.uncollided_every`` steps.

The light field adds the cache to its own in-scattering (``inscatter(...,
with_uncollided=True)``); radiance in linear RGB, SH coefficients (N, 3, (degree + 1)^2)
as :mod:`nrt.physics.sh` orders them.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from nrt.losses.context import Illumination
from nrt.modules.fields.voxel_medium import extinction
from nrt.physics.sky_light import uncollided_sh


class UncollidedCache:
    """When and how a light field's uncollided cache is refreshed, from ``samples`` (the
    stage's counts): every ``uncollided_every`` steps (and at the first), with
    ``uncollided_directions`` sky samples and ``shadow_steps`` strata per shadow ray, in
    chunks of ``uncollided_chunk`` points; the first refresh replaces the cache, later ones
    blend into it with weight ``uncollided_blend``. :attr:`fresh` says whether a refresh
    has happened (a resumed run's cache comes with its state)."""

    def __init__(self, samples: Mapping):
        self.every = int(samples["uncollided_every"])
        self.directions = int(samples["uncollided_directions"])
        self.shadow_steps = int(samples["shadow_steps"])
        self.chunk = int(samples.get("uncollided_chunk", 2048))
        self.blend = float(samples.get("uncollided_blend", 1.0))
        self.fresh = False

    def due(self, step: int) -> bool:
        """Whether ``step`` refreshes the cache: the first step, then every :attr:`every`."""
        return not self.fresh or step % self.every == 0

    @torch.no_grad()
    def refresh(self, medium, light, sky: Illumination) -> None:
        """Project the uncollided light of ``sky`` in ``medium`` at ``light``'s cache points
        into its cache (``light.set_uncollided``)."""
        sigma_t = extinction(medium)
        pts = light.cache_points()
        coef = torch.cat([uncollided_sh(pts[i:i + self.chunk], sigma_t, light.bbox,
                                        sky.rest, sky.sampler, sky.lights, light.degree,
                                        self.directions, self.shadow_steps)
                          for i in range(0, len(pts), self.chunk)])
        light.set_uncollided(coef, self.blend if self.fresh else 1.0)
