"""A grid decoder conditioned on a latent code: ``(x, z) -> MLP([f(x), z])``.

The generative stage 2 (:mod:`nrt.stages.family`) conditions its medium and its
light field on a member's latent code z by concatenation (the DeepSDF manner): ``f(x)`` are
``features`` channels trilinear on a cell-centred grid over [-1, 1]^3, shared by all codes,
and a small MLP maps ``[f(x), z]`` to the outputs (the medium's exponents and logits, or the
light's SH coefficients). The MLP's output layer starts at zero, so every code starts from
the plain component's start (zero modulation, zero scattered light).

The stages read the decoder on cells (:meth:`LatentGridDecoder.on_cells`: the outputs at
the cell centres of an R^3 grid, then trilinear between them, as the single-scene voxel
grids are read). The feature grid is the parameter ``values``, so the coarse-to-fine
schedule of :mod:`nrt.modules.fields.coarse_to_fine` resamples it as it resamples a plain grid.

With ``members`` K > 0 the decoder also holds a feature offset per member (``offsets``,
the K offsets side by side on the channels of one grid, zero at the start, resampled with
``values``): member k's outputs read ``f(x) + offset_k(x)``, a new code's ``f(x)`` alone.
:func:`fold_offsets` fits the shared features and MLP to what the members' codes and
offsets decode, so that a new code reads the members' detail too, and zeroes the offsets;
with a kernel of codes around the members it fits the decoder around each code as well.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from nrt.errors import ConfigError
from nrt.modules.fields.ea_field import mlp
from nrt.physics.volume import resample_cells, sample_grid

CHECK_DRAWS = 4
"""Draws around each code at which a fold with a kernel evaluates its objective."""
CodeKernel = Callable[[torch.Tensor, torch.Generator], torch.Tensor]
"""Codes drawn around members: (member indices (M,), a CPU generator) -> one code near
each of those members' codes (M, d_z), e.g. a smoothed bootstrap
(:meth:`~nrt.evaluation.latent_gaussian.LatentGaussian.around`)."""


class LatentGridDecoder(nn.Module):
    """``out_dim`` values at unit-box points (..., 3) under a code (..., ``latent_dim``) from
    ``features`` grid channels on ``resolution``^3 cells and an MLP of ``layers`` hidden ReLU
    layers of width ``hidden``. ``in_dim`` must be 3 (the medium's modulation factory
    signature, :class:`~nrt.modules.fields.medium.NeuralMedium`). ``members`` > 0: a feature
    offset grid per member (module docstring)."""

    def __init__(self, in_dim: int, out_dim: int, latent_dim: int, resolution: int = 8,
                 features: int = 16, hidden: int = 64, layers: int = 1,
                 init_std: float = 0.1, members: int = 0):
        super().__init__()
        if in_dim != 3:
            raise ConfigError(f"a latent grid decoder takes 3-d points, got in_dim={in_dim}.")
        for name, value, least in (("latent_dim", latent_dim, 1), ("resolution", resolution, 1),
                                   ("features", features, 1), ("hidden", hidden, 1),
                                   ("layers", layers, 1), ("members", members, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ConfigError(f"latent grid decoder: {name}={value} must be a whole "
                                  f"number >= {least} (mode.latent, model.light_field, "
                                  "model.medium).")
        self.latent_dim, self.members, self.features = latent_dim, members, features
        self.values = nn.Parameter(torch.randn(resolution, resolution, resolution, features)
                                   * init_std)
        self.offsets = (nn.Parameter(torch.zeros(resolution, resolution, resolution,
                                                 members * features)) if members else None)
        self.net = mlp(features + latent_dim, hidden, out_dim, layers)
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)
        self.register_buffer("unit_box", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    def _decode(self, features: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        if code.shape[-1] != self.latent_dim:
            raise ValueError(f"this decoder takes codes of dimension {self.latent_dim}, got "
                             f"{tuple(code.shape)}.")
        code = code.to(features).expand(*features.shape[:-1], self.latent_dim)
        return self.net(torch.cat((features, code), -1))

    def forward(self, unit: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Outputs (..., out_dim) at points of the unit box [-1, 1]^3 (..., 3) under ``code``
        (..., d_z) or one code (d_z,)."""
        return self._decode(sample_grid(self.values, unit, self.unit_box), code)

    def grids(self) -> list[nn.Parameter]:
        """The grid parameters the coarse-to-fine schedule resamples: the features and the
        members' offsets."""
        return [self.values] + ([self.offsets] if self.offsets is not None else [])

    def member_blocks(self) -> list[nn.Parameter]:
        """The members' offsets (one block of ``features`` a member along the last axis), as
        a list: [] without them."""
        return [] if self.offsets is None else [self.offsets]

    def member_offset(self, member: int) -> torch.Tensor:
        """Member ``member``'s feature offset (R, R, R, features)."""
        f = self.features
        return self.offsets[..., member * f:(member + 1) * f]

    def offset_square(self, members: torch.Tensor | None = None) -> torch.Tensor:
        """The mean over ``members`` (all when None) of the mean over the cells of
        ``|offset_k(x)|^2``: the offsets' prior, before its weight."""
        r = self.offsets.shape[0]
        per_member = self.offsets.reshape(r ** 3, self.members, self.features).square()
        per_member = per_member.sum(-1).mean(0)
        return per_member.mean() if members is None else per_member[members].mean()

    def cell_features(self, resolution: int, member: int | None = None) -> torch.Tensor:
        """The features (plus member ``member``'s offset, when given) at the centres of
        ``resolution``^3 cells (R, R, R, features), ``[z, y, x]``."""
        features = self.values
        if member is not None:
            if self.offsets is None:
                raise ValueError("this decoder holds no member offsets (members=0).")
            features = features + self.member_offset(member)
        if features.shape[0] != resolution:
            features = resample_cells(features, resolution)
        return features

    def on_cells(self, resolution: int, code: torch.Tensor, member: int | None = None
                 ) -> torch.Tensor:
        """Outputs (R, R, R, out_dim) at the centres of ``resolution``^3 cells, ``[z, y, x]``,
        under one code (d_z,): the features (plus member ``member``'s offset, when given)
        resampled to those cells (:meth:`cell_features`), then the MLP."""
        return self._decode(self.cell_features(resolution, member), code)


def fold_offsets(decoder: LatentGridDecoder, codes: torch.Tensor, weights: torch.Tensor,
                 steps: int, lr: float, cells_per_member: int = 4096, seed: int = 0,
                 kernel: CodeKernel | None = None) -> tuple[float, float]:
    """Fit ``decoder``'s shared features and MLP so that each member's code alone decodes
    what its code and its offset decode, then zero the offsets.

    ``codes`` (K, d_z) are the members' codes (held fixed); ``weights`` (K, R, R, R, 1) >= 0
    weigh the squared output error on each member's R^3 cells (a medium passes its density:
    where it is zero the outputs do not matter). The objective is the mean over members of
    ``sum_x w_k(x) |MLP([f(x), z_k]) - MLP_0([f_0(x) + offset_k(x), z_k])|^2 / sum_x w_k(x)``
    (MLP_0, f_0: the decoder before the fit). Each of the ``steps`` Adam steps estimates it
    without bias from ``cells_per_member`` cells of each member drawn in proportion to
    ``w_k`` (generator seeded with ``seed``), from the decoder as it is, the rate falling
    from ``lr`` to zero on a cosine. A member whose weight is zero on every cell (a medium
    with no density) has no output that matters and leaves the objective; the mean runs over
    the others. With a ``kernel`` (codes drawn around the members, :data:`CodeKernel`) each
    step's estimate is the mean of the one at the codes and the one at a fresh draw around
    each code, against the same member's output: the decoder is fitted around each code, not
    only at it, so that a new code drawn near a member decodes near that member's medium;
    its objective is then the mean of the one at the codes and the one at
    :data:`CHECK_DRAWS` fixed draws around each code. A fit that ends above its start (a
    rate too large for small offsets) is undone: the shared decoder stays as it was.
    Returns the objective, over every cell, before and after the fit."""
    if decoder.offsets is None:
        raise ValueError("this decoder holds no member offsets (members=0).")
    resolution = weights.shape[1]
    weights = weights.detach().reshape(codes.shape[0], -1)
    if not torch.isfinite(weights).all() or (weights < 0).any():
        raise ValueError("the fold's weights (the members' densities) must be finite and >= 0.")
    weighed = weights.sum(1) > 0
    if not weighed.any():
        raise ValueError("every member's density is zero on every cell: there is nothing to "
                         "fold.")
    kept_members = weighed.nonzero().flatten().tolist()
    codes, weights = codes.detach()[weighed], weights[weighed]
    members = codes.shape[0]
    weights = weights / weights.sum(1, keepdim=True)
    with torch.no_grad():
        targets = [decoder.on_cells(resolution, codes[i], k).reshape(weights.shape[1], -1)
                   for i, k in enumerate(kept_members)]

    def error(k: int, shared: torch.Tensor, cells: torch.Tensor | None,
              code: torch.Tensor | None = None) -> torch.Tensor:
        """Member k's squared output error on ``cells`` (all: None), (cells, out_dim), read
        at ``code`` (None: its own)."""
        at = slice(None) if cells is None else cells
        return (decoder._decode(shared[at], codes[k] if code is None else code)
                - targets[k][at]).square()

    # with a kernel, the objective also reads CHECK_DRAWS fixed draws around each code
    # (members, CHECK_DRAWS, d_z), the same before and after the fit
    checks = None if kernel is None else kernel(
        torch.tensor(kept_members).repeat_interleave(CHECK_DRAWS),
        torch.Generator().manual_seed(seed + 1)).to(codes).reshape(members, CHECK_DRAWS, -1)

    def weighed(k: int, shared: torch.Tensor, code: torch.Tensor | None = None) -> torch.Tensor:
        """Member k's error over every cell, weighed, read at ``code`` (None: its own)."""
        return (weights[k, :, None] * error(k, shared, None, code)).sum()

    def objective() -> torch.Tensor:
        shared = decoder.cell_features(resolution).reshape(-1, decoder.features)
        at_codes = torch.stack([weighed(k, shared) for k in range(members)]).mean()
        if checks is None:
            return at_codes
        around = torch.stack([weighed(k, shared, z) for k in range(members)
                              for z in checks[k]]).mean()
        return 0.5 * at_codes + 0.5 * around

    with torch.no_grad():
        start = float(objective())
        kept = [t.detach().clone() for t in (decoder.values, *decoder.net.parameters())]
    generator = torch.Generator().manual_seed(seed)
    optimiser = torch.optim.Adam([decoder.values, *decoder.net.parameters()], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, max(steps, 1))
    for _ in range(steps):
        optimiser.zero_grad(set_to_none=True)
        shared = decoder.cell_features(resolution).reshape(-1, decoder.features)
        drawn = torch.multinomial(weights.cpu(), cells_per_member, replacement=True,
                                  generator=generator).to(weights.device)
        estimate = torch.stack([error(k, shared, drawn[k]).sum(-1).mean()
                                for k in range(members)]).mean()
        if kernel is not None:
            near = kernel(torch.tensor(kept_members), generator).to(codes)
            estimate = 0.5 * estimate + 0.5 * torch.stack(
                [error(k, shared, drawn[k], near[k]).sum(-1).mean()
                 for k in range(members)]).mean()
        estimate.backward()
        optimiser.step()
        schedule.step()
    with torch.no_grad():
        decoder.offsets.zero_()
        end = float(objective())
        if end > start:  # a rate too large for offsets this small: keep the decoder as it was
            for t, old in zip((decoder.values, *decoder.net.parameters()), kept, strict=True):
                t.copy_(old)
            end = start
    decoder.zero_grad(set_to_none=True)
    return start, end
