"""The uncollided light's cache of the split stage 2 (:class:`UncollidedCache`): the SH
projection of the light that reaches a point without scattering (the sun-less sky by MIS
shadow rays, the suns and emitters by shadow rays), at a scattered-light field's cache
points, refreshed from the current medium every ``samples.uncollided_every`` steps. With
``samples.uncollided_shared``, the lights of several skies in one medium are refreshed from
one set of shadow rays (:func:`~nrt.physics.sky_light.uncollided_sh_skies`).

The light field adds the cache to its own in-scattering (``inscatter(...,
with_uncollided=True)``); radiance in linear RGB, SH coefficients (N, 3, (degree + 1)^2)
as :mod:`nrt.physics.sh` orders them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from nrt.losses.context import Illumination
from nrt.modules.fields.voxel_medium import detached, extinction
from nrt.physics.sky_light import uncollided_sh, uncollided_sh_skies


class UncollidedCache:
    """When and how a light field's uncollided cache is refreshed, from ``samples`` (the
    stage's counts): every ``uncollided_every`` steps (and at the first), with
    ``uncollided_directions`` sky samples and ``shadow_steps`` strata per shadow ray, in
    chunks of ``uncollided_chunk`` points; the first refresh replaces the cache, later ones
    blend into it with weight ``uncollided_blend``; with ``uncollided_shared`` the skies of
    one medium share their shadow rays (:meth:`refresh_all`). :attr:`fresh` says whether a
    refresh has happened (a resumed run's cache comes with its state)."""

    def __init__(self, samples: Mapping):
        self.every = int(samples["uncollided_every"])
        self.directions = int(samples["uncollided_directions"])
        self.shadow_steps = int(samples["shadow_steps"])
        self.chunk = int(samples.get("uncollided_chunk", 2048))
        self.blend = float(samples.get("uncollided_blend", 1.0))
        self.shared = bool(samples.get("uncollided_shared", False))
        self.fresh = False

    def due(self, step: int) -> bool:
        """Whether ``step`` refreshes the cache: the first step, then every :attr:`every`."""
        return not self.fresh or step % self.every == 0

    @torch.no_grad()
    def refresh_all(self, scenes: Sequence[tuple], sky_of, first: bool | None = None) -> None:
        """Refresh the light of every (medium, light) pair of ``scenes`` in its medium
        (without gradient), lit by ``sky_of(light)``: one by one (:meth:`refresh`), or with
        :attr:`shared`, the lights of one medium from one set of shadow rays. ``first``:
        whether these caches are refreshed for the first time (replaced, not blended);
        None: the first refresh of all (not :attr:`fresh`)."""
        blend = 1.0 if (not self.fresh if first is None else first) else self.blend
        if not self.shared:
            for medium, light in scenes:
                self.refresh(detached(medium), light, sky_of(light), blend)
            return
        groups: dict[int, list] = {}
        for medium, light in scenes:
            groups.setdefault(id(medium), [medium]).append(light)
        for medium, *lights in groups.values():
            self.refresh_shared(detached(medium), lights, [sky_of(li) for li in lights], blend)

    @torch.no_grad()
    def refresh_shared(self, medium, lights: Sequence, skies: Sequence[Illumination],
                       blend: float) -> None:
        """Project the uncollided light of each sky of ``skies`` in ``medium`` into the
        cache of the light beside it, all from one set of shadow rays, with weight
        ``blend``. The lights share their cache points (the per-sky lights of one
        medium)."""
        sigma_t, pts = extinction(medium), lights[0].cache_points()
        if any(not torch.equal(light.cache_points(), pts) for light in lights[1:]):
            raise ValueError("uncollided_shared: the lights of one medium need the same "
                             "cache points")
        parts = [uncollided_sh_skies(pts[i:i + self.chunk], sigma_t, lights[0].bbox,
                                     [s.rest for s in skies], [s.sampler for s in skies],
                                     [s.lights for s in skies], lights[0].degree,
                                     self.directions, self.shadow_steps)
                 for i in range(0, len(pts), self.chunk)]
        for k, light in enumerate(lights):
            light.set_uncollided(torch.cat([part[k] for part in parts]), blend)

    @torch.no_grad()
    def refresh(self, medium, light, sky: Illumination, blend: float) -> None:
        """Project the uncollided light of ``sky`` in ``medium`` at ``light``'s cache points
        into its cache (``light.set_uncollided``) with weight ``blend``."""
        sigma_t = extinction(medium)
        pts = light.cache_points()
        coef = torch.cat([uncollided_sh(pts[i:i + self.chunk], sigma_t, light.bbox,
                                        sky.rest, sky.sampler, sky.lights, light.degree,
                                        self.directions, self.shadow_steps)
                          for i in range(0, len(pts), self.chunk)])
        light.set_uncollided(coef, blend)
