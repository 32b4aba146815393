"""Equirectangular environment maps in Mitsuba's ``envmap`` convention.

``E(d)`` is the radiance seen when looking along the unit direction ``d`` from inside the
scene; light from ``d`` travels along ``-d``. Texture coordinates:

    u = atan2(d_x, -d_z) / (2 pi)  (mod 1),   v = acos(d_y) / pi   (row 0 is +Y)
    d = (sin t sin(2 pi u), cos t, -sin t cos(2 pi u)),  t = pi v

Texel placement copies Mitsuba 3.9's bilinear lookup exactly: column ``i`` is centred at
``u = (i + 0.5) / W`` and wraps around; row ``j`` sits at ``v = j / (H - 1)``, so the first
and last rows lie on the poles. A test renders an empty scene with Mitsuba and compares it
with :meth:`EnvironmentMap.lookup`, so the two cannot drift apart.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from nrt.physics.fused_envmap import fused_env_lookup, fused_env_pdf, fused_env_sample
from nrt.physics.tonemap import luminance


def direction_to_uv(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Texture coordinates ``(u, v)`` in [0, 1) x [0, 1] of unit directions ``d`` (..., 3)."""
    u = torch.atan2(d[..., 0], -d[..., 2]) / (2 * math.pi)
    u = u - torch.floor(u)
    v = torch.acos(d[..., 1].clamp(-1.0, 1.0)) / math.pi
    return u, v


def uv_to_direction(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Unit directions (..., 3) of texture coordinates ``(u, v)``."""
    theta, phi = math.pi * v, 2 * math.pi * u
    sin_t = torch.sin(theta)
    return torch.stack((sin_t * torch.sin(phi), torch.cos(theta), -sin_t * torch.cos(phi)), -1)


def texel_directions(height: int, width: int, dtype=torch.float64) -> torch.Tensor:
    """Directions (H, W, 3) at which Mitsuba places the texels of an ``H x W`` map."""
    u = (torch.arange(width, dtype=dtype) + 0.5) / width
    v = torch.arange(height, dtype=dtype) / (height - 1)
    return uv_to_direction(u[None, :].expand(height, width), v[:, None].expand(height, width))


class EnvironmentMap:
    """An RGB radiance map ``(H, W, 3)`` with Mitsuba-identical bilinear lookup."""

    def __init__(self, radiance: torch.Tensor):
        if radiance.ndim != 3 or radiance.shape[-1] != 3:
            raise ValueError(f"environment map must be (H, W, 3), got {tuple(radiance.shape)}")
        if radiance.shape[0] < 3 or radiance.shape[1] < 2:
            raise ValueError("environment map must be at least 3 rows x 2 columns (Mitsuba)")
        self.radiance = radiance

    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]

    def to(self, *args, **kwargs) -> EnvironmentMap:
        return EnvironmentMap(self.radiance.to(*args, **kwargs))

    def lookup(self, d: torch.Tensor) -> torch.Tensor:
        """Radiance ``E(d)`` (..., 3) seen looking along unit directions ``d`` (..., 3), in
        the map's dtype (with ``fused_lookups``, one C++ pass: :mod:`nrt.physics.fused_envmap`)."""
        fused = fused_env_lookup(self.radiance, d)
        if fused is not None:
            return fused
        h, w = self.height, self.width
        u, v = direction_to_uv(d.to(self.radiance.dtype))
        x = u - 0.5 / w
        x = (x - torch.floor(x)) * w  # in [0, w): column index space with wrap-around
        y = v * (h - 1)
        x0 = torch.floor(x).clamp(0, w - 1)
        y0 = torch.floor(y).clamp(0, h - 2)
        wx, wy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
        x0, y0 = x0.long(), y0.long()
        x1 = (x0 + 1) % w  # the padded column equals column 0
        img = self.radiance
        top = img[y0, x0] * (1 - wx) + img[y0, x1] * wx
        bottom = img[y0 + 1, x0] * (1 - wx) + img[y0 + 1, x1] * wx
        return top * (1 - wy) + bottom * wy


class EnvironmentDirectionSampler:
    """Look directions ``d`` drawn in proportion to ``E(d)`` with an exactly known density.

    The sphere is cut into cells around Mitsuba's texels (column ``i`` spans ``u`` in
    ``[i, i + 1) / W``; row ``j`` the polar band between its neighbours' midpoints, clipped
    at the poles). A cell is drawn with probability ``(lum(E_ij) + floor) * Omega_ij``,
    then a direction uniform in solid angle inside it, so :meth:`pdf` (per steradian) is
    the cell's probability over its solid angle (a cell is drawn by inverting the cells'
    cumulative probabilities at a uniform number). A cell's luminance is the largest of its
    texel's 3 x 3 neighbours (the bilinear lookup spreads a bright texel into the cells
    beside it, which would otherwise be drawn too rarely). The small floor (``floor_fraction`` of
    the mean luminance) keeps every direction reachable, as multiple importance sampling
    needs. Used for inflow samples on the box faces and for the sky's first scattering.
    """

    def __init__(self, envmap: EnvironmentMap, floor_fraction: float = 1e-3):
        h, w = envmap.height, envmap.width
        rows = torch.arange(h, dtype=torch.float64)
        self.cos_top = torch.cos(torch.pi * ((rows - 0.5) / (h - 1)).clamp(0.0, 1.0))
        self.cos_bottom = torch.cos(torch.pi * ((rows + 0.5) / (h - 1)).clamp(0.0, 1.0))
        solid = (self.cos_top - self.cos_bottom)[:, None] * (2 * torch.pi / w)  # (h, 1)
        lum = luminance(envmap.radiance.double()).clamp_min(0.0)
        wrapped = torch.cat((lum[:, -1:], lum, lum[:, :1]), 1)[None, None]  # u wraps around
        lum = F.max_pool2d(F.pad(wrapped, (0, 0, 1, 1), mode="replicate"), 3, 1)[0, 0]
        weights = (lum + floor_fraction * lum.mean().clamp_min(1e-30)) * solid
        self.probs = (weights / weights.sum()).flatten()
        self.cdf = torch.cumsum(self.probs, 0)
        self.density = (self.probs.reshape(h, w) / solid).float()  # per steradian
        self.height, self.width = h, w

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` unit look directions (n, 3), float32 on the CPU, from ``n`` x 3 uniform
        numbers: the cell (the first whose cumulative probability exceeds the first), the
        polar and the azimuthal position in it (with ``fused_lookups``, one C++ pass)."""
        xi = torch.rand(n, 3, dtype=torch.float64, generator=generator)
        fused = fused_env_sample(self.cdf, self.cos_top, self.cos_bottom, self.width, xi)
        if fused is not None:
            return fused
        idx = torch.searchsorted(self.cdf, xi[:, 0].contiguous(), right=True)
        idx = idx.clamp_max(len(self.cdf) - 1)
        row, col = idx // self.width, idx % self.width
        cos = self.cos_top[row] + xi[:, 1] * (self.cos_bottom[row] - self.cos_top[row])
        cos = cos.clamp(-1.0, 1.0)
        sin = (1 - cos * cos).clamp_min(0.0).sqrt()
        phi = (col + xi[:, 2]) * (2 * math.pi / self.width)
        return torch.stack((sin * torch.sin(phi), cos, -sin * torch.cos(phi)), -1).float()

    def pdf(self, d: torch.Tensor) -> torch.Tensor:
        """Density per steradian (...,) of drawing the unit look directions ``d`` (..., 3)."""
        fused = fused_env_pdf(self.density, d)
        if fused is not None:
            return fused
        u, v = direction_to_uv(d)
        col = (u * self.width).long().clamp(0, self.width - 1)
        row = torch.round(v * (self.height - 1)).long().clamp(0, self.height - 1)
        return self.density.to(d.device)[row, col].to(d.dtype)
