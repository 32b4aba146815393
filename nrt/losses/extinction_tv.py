"""Total variation of the extinction: an edge-keeping smoothness prior of split stage 2.

The photos weigh some of the medium's texture weakly: the profile of a thick white body
along its normal, detail near a pixel's footprint (docs/stage2.md, "The photos' noise").
Along those directions the fit follows the photos' own Monte Carlo noise, a fixed offset
per pixel that no number of steps averages away. Total variation, the classic prior of
tomography from noisy projections, lowers that variance: it charges a voxel grid for the
summed size of its gradients, so noise-like texture costs much and a sharp edge (one
large step) costs no more than a gradual one of the same height.

The loss is ``mean over cells of sqrt(|grad sigma_t|^2 + eps^2) - eps``, with ``sigma_t``
the channel mean and ``grad`` forward differences over the cell size (scene length units,
so the loss is in inverse squared length and does not change with the grid's
resolution). ``eps`` (the same units) keeps the gradient of the square root finite where
the extinction is flat. Off by default (``ablation=extinction_tv`` adds it at 1e-5): on the
`cpu` preset it lowers `heldout2`'s end by 10-15 % and changes five other scenes by -1 to
+2 % (docs/stage2.md, "A total-variation prior", "A third blind scene").
"""

from __future__ import annotations

import torch

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective

EPS = 1e-2
"""Smoothing of ``|grad sigma_t|`` (inverse squared length): well below the gradient of any
texture the photos resolve (sigma_t ~0.1 over a cell of 1/32 of a 2-unit box: ~1.6)."""


def total_variation(extinction: torch.Tensor, bbox: torch.Tensor, eps: float = EPS) -> torch.Tensor:
    """``mean sqrt(|grad s|^2 + eps^2) - eps`` of ``s``, the channel mean of ``extinction``
    (R, R, R, C) in ``[z, y, x]`` on cells of the box ``bbox`` (2, 3), by forward
    differences over the (R - 1)^3 cells that have all three neighbours."""
    s = extinction.mean(-1)
    r = s.shape[0]
    cell = (bbox[1] - bbox[0]).flip(0).to(s) / r  # [z, y, x] cell sizes
    dz = (s[1:, :-1, :-1] - s[:-1, :-1, :-1]) / cell[0]
    dy = (s[:-1, 1:, :-1] - s[:-1, :-1, :-1]) / cell[1]
    dx = (s[:-1, :-1, 1:] - s[:-1, :-1, :-1]) / cell[2]
    return (torch.sqrt(dz.square() + dy.square() + dx.square() + eps ** 2) - eps).mean()


class ExtinctionTV(Objective):
    """``extinction_tv``: :func:`total_variation` of each learned medium's extinction (the
    step's ``context.voxel_media``), averaged over them. It trains the medium only; off unless
    weighted (``ablation=extinction_tv``)."""

    families = True
    medium_only = True
    reads_voxels = True

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        return torch.stack([total_variation(voxels.extinction, voxels.bbox)
                            for voxels in context.voxel_media(self.name)]).mean()
