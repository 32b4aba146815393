"""The medium of split stage 2: the EA density modulated on voxels, coarse to fine.

``sigma_t = rho exp(t)`` per channel (one when grey) and ``albedo = sigmoid(b)``
(``parametrization=extinction``, stage 2's default; ``scattering``: ``sigma_a = rho
exp(a)``, ``sigma_s = rho exp(s)``), ``g`` one shared value (``phase=hg``) or ``G_MAX
tanh(h)`` per voxel (``varying_hg``), as in :class:`~nrt.modules.fields.medium.NeuralMedium`,
whose heads this class shares. ``rho`` is the frozen EA density baked once onto ``R``^3
cells (:meth:`set_density`); the modulation (exponents and logits) lives on a coarser
grid that doubles during training (``resolutions`` at the run's fractions ``upsample_at``,
:meth:`VoxelMedium.follow_schedule`; :mod:`nrt.modules.fields.coarse_to_fine`, as the
path-tracing baseline does).

It is the split stage's medium (``conf/model/medium/voxel.yaml``; the protocol:
:class:`~nrt.modules.fields.protocols.VoxelisedMedium`). :class:`LatentVoxelMedium` is its
generative version: one baked density per family member, the modulation decoded from a
latent code (:class:`~nrt.modules.fields.latent_grid.LatentGridDecoder`).

Transport queries the medium many times per step (shadow rays, marches), so the properties
are composed once on the ``R``^3 cells (:meth:`voxels`, differentiable) and then read by a
single trilinear lookup each: :class:`Voxels`. Between cell centres the properties
interpolate linearly, as Mitsuba's grid volumes do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import torch
from torch import nn
from torch.profiler import record_function

from nrt.modules.fields.coarse_to_fine import check_schedule, resample_parameter, resolution_at
from nrt.modules.fields.latent_grid import CodeKernel, LatentGridDecoder, fold_offsets
from nrt.modules.fields.medium import GridModulation, MediumProperties, NeuralMedium
from nrt.physics.volume import GridExtinction, at_cell_centres, resample_cells, sample_grid


class Voxels:
    """Properties composed on cells: ``stacked`` (R, R, R, C + 3 [+ 1]) holds sigma_t (C = 3,
    or 1 when grey), the RGB albedo and, for a g field, g; ``g_shared`` a scalar or None.
    Callable like a :class:`~nrt.modules.fields.medium.Medium` (``voxels(x)`` ->
    :class:`MediumProperties`); :attr:`sigma_t` reads only the extinction."""

    def __init__(self, stacked: torch.Tensor, channels: int, phase: str,
                 g_shared: torch.Tensor | None, bbox: torch.Tensor):
        self.stacked, self.channels, self.phase = stacked, channels, phase
        self.extinction = stacked[..., :channels].contiguous()
        self.g_shared, self.bbox = g_shared, bbox
        self.sigma_t = GridExtinction(self.extinction, bbox)
        """The extinction alone: ``sigma_t(x (..., 3)) -> (..., C)``, marched fused by
        :func:`~nrt.physics.volume.optical_depth`."""

    def detached(self) -> Voxels:
        """The same voxels without gradient (targets and caches computed from them)."""
        g = None if self.g_shared is None else self.g_shared.detach()
        return Voxels(self.stacked.detach(), self.channels, self.phase, g, self.bbox)

    def as_leaf(self) -> Voxels:
        """The same values as leaves of a graph of their own: objectives that read them leave
        their gradients on the leaves, and :meth:`carried_back` takes the sum of those
        through this voxels' own graph in one backward."""
        g = None if self.g_shared is None else self.g_shared.detach().requires_grad_()
        return Voxels(self.stacked.detach().requires_grad_(), self.channels, self.phase, g,
                      self.bbox)

    def carried_back(self, leaf: Voxels) -> torch.Tensor | None:
        """A scalar whose gradient through this voxels' graph is the gradient ``leaf`` (its
        :meth:`as_leaf`) received: ``sum(stacked * leaf.stacked.grad)`` (plus the shared
        g's term); None when the leaf received none."""
        terms = [(value * copy.grad).sum()
                 for value, copy in ((self.stacked, leaf.stacked), (self.g_shared, leaf.g_shared))
                 if copy is not None and copy.grad is not None and value.requires_grad]
        return torch.stack(terms).sum() if terms else None

    def __call__(self, x: torch.Tensor) -> MediumProperties:
        with record_function("nrt/medium"):
            v = sample_grid(self.stacked, x, self.bbox)
            c = self.channels
            sigma_t, albedo = v[..., :c], v[..., c:c + 3]
            if self.phase == "field":
                g = v[..., c + 3]
            elif self.phase == "shared":
                g = self.g_shared.expand(x.shape[:-1])
            else:
                g = None
            return MediumProperties(sigma_t * (1 - albedo), sigma_t * albedo, albedo, g,
                                    extinction=sigma_t if c == 1 else None)


def extinction(medium) -> Callable[[torch.Tensor], torch.Tensor]:
    """``x -> sigma_t`` of a medium: one lookup for :class:`Voxels`, the properties
    otherwise."""
    return medium.sigma_t if isinstance(medium, Voxels) else (lambda x: medium(x).sigma_t)


def detached(medium):
    """The medium without gradient: :class:`Voxels` detached; any other (a ground truth)
    as it is."""
    return medium.detached() if isinstance(medium, Voxels) else medium


@torch.no_grad()
def bake(density: Callable[[torch.Tensor], torch.Tensor], resolution: int,
         bbox: torch.Tensor) -> torch.Tensor:
    """``density(points (N, 3)) -> (N,)`` at the centres of ``resolution``^3 cells of
    ``bbox``, clamped at 0: (R, R, R, 1), ``[z, y, x]``."""
    return at_cell_centres(density, resolution, bbox).unsqueeze(-1).clamp_min(0.0)


class VoxelMedium(NeuralMedium):
    """EA density (baked on ``density_resolution``^3 cells) times a grid modulation of
    ``resolutions[k]``^3 cells from the run's fraction ``upsample_at[k - 1]`` on.
    ``modulation(in_dim, out_dim, resolution=...)`` builds that grid (by default a
    :class:`~nrt.modules.fields.medium.GridModulation`); its ``grids()`` are resampled."""

    def __init__(self, effects: dict, resolutions: Sequence[int] = (8,),
                 upsample_at: Sequence[float] = (), density_resolution: int = 64,
                 init_albedo: float = 0.8, parametrization: str = "scattering",
                 modulation: Callable[..., torch.nn.Module] = GridModulation):
        check_schedule(resolutions, upsample_at,
                       "budget.rte.medium_resolutions / medium_upsample_at")
        super().__init__(effects, None, partial(modulation, resolution=resolutions[0]),
                         init_albedo=init_albedo, parametrization=parametrization)
        self.resolutions, self.upsample_at = tuple(resolutions), tuple(upsample_at)
        r = density_resolution
        self.register_buffer("density", torch.ones(r, r, r, 1))

    @property
    def resolution(self) -> int:
        """Cells per axis of the modulation grid now."""
        return self.modulation.values.shape[0]

    def follow_schedule(self, progress: float, optimizer: torch.optim.Optimizer | None) -> bool:
        """Resample the modulation to its scheduled resolution at ``progress`` in [0, 1],
        restarting its ``optimizer`` state; True when the resolution changed."""
        res = resolution_at(progress, self.resolutions, self.upsample_at)
        if res == self.resolution:
            return False
        for grid in self.modulation.grids():
            resample_parameter(grid, optimizer, res)
        return True

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        """A checkpoint holds the modulation at the resolution its run had reached: resize the
        grids to it before the values are loaded (the module's own hook, before its
        children's)."""
        resampled = {id(g) for g in self.modulation.grids()}
        for name, grid in self.modulation.named_parameters():
            saved = state_dict.get(f"{prefix}modulation.{name}")
            if saved is not None and id(grid) in resampled:
                grid.data = torch.zeros_like(saved)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def set_density(self, density) -> None:
        """Bake ``density(points (N, 3)) -> (N,)`` (the EA field's) at the cell centres."""
        self.density.copy_(bake(density, self.density.shape[0],
                                self.bbox.to(self.density.device)))

    def rho(self, x: torch.Tensor) -> torch.Tensor:
        return sample_grid(self.density, x, self.bbox)[..., 0]

    def voxels(self) -> Voxels:
        """The properties on the density's cells (differentiable in the modulation)."""
        with record_function("nrt/medium"):
            r = self.density.shape[0]
            return self.compose(self.density, resample_cells(self.modulation.values, r))

    def compose(self, density: torch.Tensor, h: torch.Tensor,
                g_logit: torch.Tensor | None = None) -> Voxels:
        """:class:`Voxels` of a density (R, R, R, 1) and the modulation's raw outputs on the
        same cells (R, R, R, n), offsets not yet added (``g_logit``: :meth:`heads`)."""
        props = self.heads(density, h + self.offsets, g_logit)
        parts = [props.sigma_t, props.albedo]
        if self.phase == "field":
            parts.append(props.g.unsqueeze(-1))
        g_shared = props.g.reshape(-1)[0] if self.phase == "shared" else None
        return Voxels(torch.cat(parts, -1), self.channels, self.phase, g_shared, self.bbox)

    def forward(self, x: torch.Tensor) -> MediumProperties:
        return self.voxels()(x)



class LatentVoxelMedium(VoxelMedium):
    """The voxel medium of a scene family conditioned on latent codes (generative stage 2):
    a density on ``density_resolution``^3 cells that the stage supplies per member (the EA
    density under the member's code), modulated by the exponents and logits that a
    :class:`~nrt.modules.fields.latent_grid.LatentGridDecoder` decodes from the shared feature grid
    (coarse to fine, as the plain modulation grid) and the code z (``features`` channels, an
    MLP of ``layers`` hidden layers of width ``hidden``). It holds no density itself.

    A shared g (``phase: hg``) is one parameter for every code, unless ``g_from_code``: then
    each code has its own, ``g = G_MAX tanh(g_shared + w . z)`` with ``w`` starting at zero
    (every code starts from the plain medium's g), as each member of a family has its own
    g. With ``member_offsets`` the decoder's features carry a zero-started offset for each
    of the ``members`` (:meth:`voxels_for` with ``member``), under the prior the stage
    weighs (:meth:`offset_square`); a new code decodes without one."""

    def __init__(self, effects: dict, latent_dim: int, features: int = 16, hidden: int = 64,
                 layers: int = 1, resolutions: Sequence[int] = (8,),
                 upsample_at: Sequence[float] = (), density_resolution: int = 64,
                 init_albedo: float = 0.8, parametrization: str = "extinction",
                 g_from_code: bool = False, members: int = 0, member_offsets: bool = False):
        decoder = partial(LatentGridDecoder, latent_dim=latent_dim, features=features,
                          hidden=hidden, layers=layers, members=members if member_offsets else 0)
        super().__init__(effects, resolutions, upsample_at, density_resolution, init_albedo,
                         parametrization, modulation=decoder)
        del self.density  # supplied per member and code by the stage
        self.density_resolution = int(density_resolution)
        self.g_weights = (nn.Parameter(torch.zeros(latent_dim))
                          if g_from_code and self.phase == "shared" else None)

    @property
    def member_offsets(self) -> int:
        """How many members hold a feature offset (0: none)."""
        return self.modulation.members

    def member_blocks(self) -> list[nn.Parameter]:
        """The members' feature offsets, one block a member along the last axis ([]: none)."""
        return self.modulation.member_blocks()

    def offset_square(self, members: torch.Tensor | None = None) -> torch.Tensor:
        """The mean over ``members`` (None: all) of the mean over cells of ``|offset_k|^2``."""
        return self.modulation.offset_square(members)

    def fold_offsets(self, densities: torch.Tensor, codes: torch.Tensor, steps: int,
                     lr: float, kernel: CodeKernel | None = None) -> tuple[float, float]:
        """Fit the shared decoder to the members' media, offsets included, weighing each
        member's cells by its density (K, R, R, R, 1) under its code (K, d_z), at the codes
        and, with a ``kernel``, around them, and zero the offsets
        (:func:`~nrt.modules.fields.latent_grid.fold_offsets`): the fit's objective before
        and after."""
        return fold_offsets(self.modulation, codes, densities, steps, lr, kernel=kernel)

    def voxels_for(self, density: torch.Tensor, code: torch.Tensor,
                   member: int | None = None) -> Voxels:
        """The properties of a density (R, R, R, 1) modulated under ``code`` (d_z,), with
        member ``member``'s feature offset when given, on the density's cells
        (differentiable in the density, the decoder, the offset and the code)."""
        h = self.modulation.on_cells(density.shape[0], code, member)
        if self.g_weights is None:
            return self.compose(density, h)
        return self.compose(density, h, self.g_shared + self.g_weights @ code.to(h))

    def voxels(self) -> Voxels:
        raise TypeError(NO_DENSITY)

    def rho(self, x: torch.Tensor) -> torch.Tensor:
        raise TypeError(NO_DENSITY)

    def set_density(self, density) -> None:
        raise TypeError(NO_DENSITY)


NO_DENSITY = ("a latent voxel medium holds no density of its own (one per family member and "
              "code): use voxels_for(density, code).")
