"""Extinction prior of split stage 2: the mean extinction over the medium's voxels.

Where the photos cannot see, they do not constrain the medium: behind an optical depth of
a few, inside a dense core, a brighter or darker interior changes no pixel (a thick enough
scattering slab reflects the same light whatever its extinction). There the EA start
keeps whatever stage 1 put, often several times the truth (docs/stage2.md, "Dense
cores"). This prior, ``mean over voxels of sigma_t`` (the channel mean, in the scene's
inverse length units), is the least-extinction choice among media the photos cannot tell
apart: where a pixel depends on a voxel the photo objective holds it, elsewhere the prior
lowers it. Its gradient with respect to a voxel's exponent ``t`` (``sigma_t = rho exp(t)``)
is proportional to that voxel's extinction, so it acts mostly on the densest voxels.

With a ``saturation`` s (the same units) each voxel costs ``s log(1 + sigma_t / s)``
instead: the same as ``sigma_t`` where the extinction is well below s, growing only
logarithmically above it. Its gradient with respect to ``t`` is ``s sigma_t / (s +
sigma_t)``, at most s: at ten times the weight and s = 0.5 a dense core (sigma_t ~5) is
pushed about as hard as by the plain prior and a thin cell (sigma_t ~0.2) seven times
harder. It is a sparsity prior: a medium blurred by its photos' pixels (a thin halo around
denser cores, each cell weakly seen) loses the halo first.
"""

from __future__ import annotations

import math

import torch

from nrt.errors import ConfigError
from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule


class ExtinctionPrior(Objective):
    """``extinction_prior``: the mean over voxels and channels of the extinction of each
    learned medium (the step's ``context.voxel_media``: one for a scene under several skies,
    one per member for a family), averaged over them; with ``saturation`` s (inverse length,
    ``losses.objectives.extinction_prior.saturation``) the mean of ``s log(1 + sigma_t /
    s)``. It trains the medium only."""

    families = True
    medium_only = True
    reads_voxels = True

    def __init__(self, name: str, schedule: WeightSchedule, saturation: float | None = None):
        super().__init__(name, schedule)
        number = isinstance(saturation, int | float) and not isinstance(saturation, bool)
        if saturation is not None and not (number and math.isfinite(saturation)
                                           and saturation > 0):
            raise ConfigError(
                f"losses.objectives.{name}.saturation={saturation}: the extinction (inverse "
                "length) above which the prior grows only logarithmically, a finite number "
                "> 0, or null for the plain mean extinction.")
        self.saturation = None if saturation is None else float(saturation)

    def penalty(self, extinction: torch.Tensor) -> torch.Tensor:
        """The prior of one medium's extinction (any shape): its mean, or the mean of
        ``s log(1 + sigma_t / s)`` with a saturation s."""
        if self.saturation is None:
            return extinction.mean()
        s = self.saturation
        return (s * torch.log1p(extinction.clamp_min(0) / s)).mean()

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        return torch.stack([self.penalty(voxels.extinction)
                            for voxels in context.voxel_media(self.name)]).mean()
