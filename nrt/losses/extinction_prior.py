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
"""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective


class ExtinctionPrior(Objective):
    """``extinction_prior``: the mean over voxels and channels of the extinction of each
    learned medium (the step's ``context.voxel_media``: one for a scene under several skies,
    one per member for a family), averaged over them. It trains the medium only."""

    families = True
    medium_only = True
    reads_voxels = True

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        return torch.stack([voxels.extinction.mean()
                            for voxels in context.voxel_media(self.name)]).mean()
