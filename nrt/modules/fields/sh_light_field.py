"""Scattered light as spherical harmonics on a grid: the light field of split stage 2.

The radiance splits into the uncollided part ``L_u`` (the environment and the known
lights attenuated by the medium, computed exactly by :mod:`nrt.physics.sky_light` and
:mod:`nrt.physics.direct_light`) and the light scattered at least once, ``L_s``, which this
field learns: zero inflow on the box, smooth in direction, so a few SH bands hold it,

    L_s(x, w) = sum_lm c_lm(x) Y_lm(w)    (radiance at x travelling along w),

with ``c`` (RGB, in units of ``radiance_scale``) trilinear on a cell-centred grid over the
medium box. Henyey-Greenstein scales band ``l`` by ``g^l``, so the in-scattered radiance of
``L_s`` is exact and needs no direction samples (:meth:`inscatter`).

The field also holds ``uncollided``: the SH projection of ``L_u`` on the same grid, a cache
refreshed from the current medium by the stage (:meth:`set_uncollided`). With it the
in-scattering of *all* light, ``sum g^l (u_lm + c_lm) Y_lm(w)``, costs two grid lookups,
which makes the transport target (:mod:`nrt.losses.transport`) cheap to march.

It is the split stage's default light field (``conf/model/light_field/sh_grid.yaml``; the
protocol: :class:`~nrt.modules.fields.protocols.ScatteredLightField`). The lookups live in
:class:`SHGrid`, the coefficients of one scene as plain tensors, which the field reads its
own parameters through; :class:`LatentSHGridLightField` (generative stage 2) decodes one such
grid per latent code.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.profiler import record_function

from nrt.errors import ConfigError
from nrt.modules.fields.latent_grid import LatentGridDecoder
from nrt.physics.sh import num_coefficients, phase_band_factors, sh_basis
from nrt.physics.volume import cell_centres, sample_grid


def sh_degree(degree: int, resolution: int, effects: dict | None) -> int:
    """The SH degree a light field keeps: ``degree``, or 0 for an isotropic phase (its
    in-scattering reads no other band); refuses ``degree < 0`` and ``resolution < 2``."""
    if degree < 0 or resolution < 2:
        raise ConfigError(f"model.light_field needs degree >= 0 and resolution >= 2, got "
                          f"{degree} and {resolution}.")
    return 0 if (effects or {}).get("phase") == "isotropic" else degree


class SHGrid:
    """One scene's scattered light as tensors: ``coefficients`` and the ``uncollided``
    cache (R, R, R, 3 (degree + 1)^2) in units of ``radiance_scale``, on cells over
    ``bbox``. Its methods are :class:`SHGridLightField`'s; :meth:`set_uncollided` writes
    into ``uncollided`` in place (a view of a field's buffer)."""

    def __init__(self, coefficients: torch.Tensor, uncollided: torch.Tensor, degree: int,
                 bbox: torch.Tensor, radiance_scale: torch.Tensor):
        self.coefficients, self.uncollided, self.degree = coefficients, uncollided, degree
        self.bbox, self.radiance_scale = bbox, radiance_scale

    @property
    def resolution(self) -> int:
        return self.coefficients.shape[0]

    def cache_points(self) -> torch.Tensor:
        """The cell centres (R^3, 3), ``[z, y, x]`` order: where the uncollided light's SH
        coefficients are stored (:meth:`set_uncollided`)."""
        return cell_centres(self.resolution, self.bbox).reshape(-1, 3)

    def _lookup(self, grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        c = sample_grid(grid, x, self.bbox)
        return c.reshape(*x.shape[:-1], 3, num_coefficients(self.degree)) * self.radiance_scale

    def __call__(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Scattered radiance ``L_s(x, w)`` (..., 3) at points ``x`` along travel ``w``."""
        with record_function("nrt/light_field"):  # a profiler scope (benchmarks.profile_step)
            return (self._lookup(self.coefficients, x) * sh_basis(w, self.degree).unsqueeze(-2)
                    ).sum(-1)

    def inscatter(self, x: torch.Tensor, w: torch.Tensor, g: torch.Tensor | None,
                  with_uncollided: bool = False, trainable: bool = True) -> torch.Tensor:
        """``int f(w' . w) L(x, w') dw'`` (..., 3) of ``L_s`` (and of the cached uncollided
        light with ``with_uncollided``), exact for HG of ``g`` (...,) or isotropic (None).
        ``trainable=False`` keeps gradients from the coefficients (not from ``g``)."""
        with record_function("nrt/light_field"):
            grid = self.coefficients if trainable else self.coefficients.detach()
            if with_uncollided:
                grid = grid + self.uncollided
            basis = sh_basis(w, self.degree) * phase_band_factors(g, self.degree).to(w)
            return (self._lookup(grid, x) * basis.unsqueeze(-2)).sum(-1)

    @torch.no_grad()
    def set_uncollided(self, coefficients: torch.Tensor, blend: float = 1.0) -> None:
        """Store the uncollided light's SH coefficients at the cell centres, (R^3, 3, K) in
        radiance units, ``[z, y, x]`` order; ``blend < 1`` averages them with the cache
        (an exponential moving average over refreshes: less Monte Carlo noise)."""
        r = self.resolution
        new = (coefficients / self.radiance_scale).reshape(r, r, r, -1)
        self.uncollided.mul_(1 - blend).add_(blend * new)


class SHGridLightField(nn.Module):
    """``L_s(x, w)`` (..., 3) from SH coefficients of ``degree`` on ``resolution``^3 cells.
    With the scene's ``effects``, an isotropic phase keeps band 0 only: its in-scattering
    reads no other band (docs/conventions.md, "Scene effects"). The methods are
    :class:`SHGrid`'s, on the field's parameters."""

    def __init__(self, degree: int = 2, resolution: int = 16, effects: dict | None = None):
        super().__init__()
        self.degree = sh_degree(degree, resolution, effects)
        k = 3 * num_coefficients(self.degree)
        self.coefficients = nn.Parameter(torch.zeros(resolution, resolution, resolution, k))
        self.register_buffer("uncollided", torch.zeros(resolution, resolution, resolution, k))
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        self.register_buffer("radiance_scale", torch.tensor(1.0))

    @property
    def resolution(self) -> int:
        return self.coefficients.shape[0]

    def grid(self) -> SHGrid:
        """The field as an :class:`SHGrid` (its parameters and cache, not copies)."""
        return SHGrid(self.coefficients, self.uncollided, self.degree, self.bbox,
                      self.radiance_scale)

    def cache_points(self) -> torch.Tensor:
        return self.grid().cache_points()

    def forward(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return self.grid()(x, w)

    def inscatter(self, x: torch.Tensor, w: torch.Tensor, g: torch.Tensor | None,
                  with_uncollided: bool = False, trainable: bool = True) -> torch.Tensor:
        return self.grid().inscatter(x, w, g, with_uncollided, trainable)

    def set_uncollided(self, coefficients: torch.Tensor, blend: float = 1.0) -> None:
        self.grid().set_uncollided(coefficients, blend)


class LatentSHGridLightField(nn.Module):
    """The scattered light of ``members`` scenes conditioned on latent codes (generative stage
    2): the SH coefficients on ``resolution``^3 cells are decoded from shared grid features
    of x concatenated with a code z (:class:`~nrt.modules.fields.latent_grid.LatentGridDecoder`:
    ``features`` channels, an MLP of ``layers`` hidden layers of width ``hidden``, zero at
    the start as the plain field is), and each member keeps its own uncollided cache.
    :meth:`member` gives one member's light as an :class:`SHGrid`. With ``member_offsets``
    each member's light also reads a feature offset of its own (zero at the start, free:
    only the members' media are ever sampled)."""

    def __init__(self, members: int, latent_dim: int, degree: int = 2, resolution: int = 16,
                 features: int = 16, hidden: int = 64, layers: int = 1,
                 effects: dict | None = None, member_offsets: bool = False):
        super().__init__()
        self.degree = sh_degree(degree, resolution, effects)
        k = 3 * num_coefficients(self.degree)
        self.decoder = LatentGridDecoder(3, k, latent_dim, resolution, features, hidden, layers,
                                         members=members if member_offsets else 0)
        self.register_buffer("uncollided",
                             torch.zeros(members, resolution, resolution, resolution, k))
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        self.register_buffer("radiance_scale", torch.tensor(1.0))

    def member_blocks(self) -> list[nn.Parameter]:
        """The members' feature offsets, one block a member along the last axis ([]: none)."""
        return self.decoder.member_blocks()

    @property
    def resolution(self) -> int:
        return self.uncollided.shape[1]

    def decode(self, code: torch.Tensor, member: int | None = None) -> torch.Tensor:
        """The coefficients (R, R, R, 3 (degree + 1)^2) that code ``code`` (d_z,) decodes to
        (with member ``member``'s feature offset when given)."""
        return self.decoder.on_cells(self.resolution, code, member)

    def member(self, index: int, code: torch.Tensor) -> SHGrid:
        """Member ``index``'s light: the coefficients of ``code`` (and the member's offset,
        where the field holds them; differentiable in the decoder and the code) and the
        member's uncollided cache (a view of the buffer)."""
        offset = index if self.decoder.members else None
        return SHGrid(self.decode(code, offset), self.uncollided[index], self.degree,
                      self.bbox, self.radiance_scale)
