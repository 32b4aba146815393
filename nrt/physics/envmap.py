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
        """Radiance ``E(d)`` (..., 3) seen looking along unit directions ``d`` (..., 3)."""
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
