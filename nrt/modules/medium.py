"""Media of stage 2: ``x -> (sigma_a, sigma_s, g)``, built for exactly the scene's effects.

Heads follow the scene's declared effects (DESIGN.md "simulate only what a scene calls
for"): ``phase=isotropic`` has no g at all, ``phase=hg`` one shared learnable g,
``phase=varying_hg`` a g field; ``chromatic=false`` gives one grey channel that broadcasts
over RGB. Units: sigma per unit world length; g in [-G_MAX, G_MAX].

- :class:`NeuralMedium`: ``sigma_a = rho(x) exp(a(x))``, ``sigma_s = rho(x) exp(s(x))``,
  ``g = G_MAX tanh(h(x))``, with ``rho`` the EA density (or 1 without a first stage) and
  ``(a, s, h)`` from a SIREN or, for the paper's ablation, a trilinear grid.
  Exponents are clamped so exp never overflows; ``albedo = sigmoid(s - a)`` is exact
  without dividing by a small sigma_t.
- :class:`GroundTruthMedium`: the dataset's grids (forward mode, tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from nrt.modules.siren import Siren
from nrt.physics.phase import G_MAX
from nrt.physics.volume import cell_centres, sample_grid

PHASE_HEADS = {"isotropic": "none", "hg": "shared", "varying_hg": "field"}
"""How each declared phase is represented: no g, one shared g, or a g field."""

EXPONENT_RANGE = (-15.0, 10.0)
"""Clamp of the exponents ``a, s``: exp stays within [3e-7, 2.2e4] times the density."""


@dataclass
class MediumProperties:
    """Optical properties at a batch of points: ``sigma_a``, ``sigma_s`` (..., C) with C = 3
    (chromatic) or 1 (grey, broadcasts over RGB), ``albedo`` = sigma_s / sigma_t (..., C)
    and ``g`` (...,) or None for an isotropic phase."""

    sigma_a: torch.Tensor
    sigma_s: torch.Tensor
    albedo: torch.Tensor
    g: torch.Tensor | None

    @property
    def sigma_t(self) -> torch.Tensor:
        return self.sigma_a + self.sigma_s


def scene_channels(effects: dict) -> int:
    """Colour channels of the medium: 3 for chromatic scenes, 1 for grey ones."""
    return 3 if effects.get("chromatic", True) else 1


def phase_head(effects: dict) -> str:
    phase = effects.get("phase", "hg")
    if phase not in PHASE_HEADS:
        raise ValueError(f"scene.effects.phase must be one of {sorted(PHASE_HEADS)}, "
                         f"got '{phase}'")
    return PHASE_HEADS[phase]


class Medium(nn.Module):
    """Base of every medium: ``forward(x) -> MediumProperties`` at world points (..., 3)."""

    def __init__(self, effects: dict):
        super().__init__()
        self.channels = scene_channels(effects)
        self.phase = phase_head(effects)
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    @torch.no_grad()
    def grids(self, resolution: int, chunk: int = 65536) -> dict[str, torch.Tensor]:
        """Properties at the box's cell centres, ``[z, y, x]``-indexed like the dataset's
        ground truth: ``sigma_a``, ``sigma_s`` (R, R, R, 3) and ``g`` (R, R, R)."""
        pts = cell_centres(resolution, self.bbox).reshape(-1, 3)
        parts = [self(pts[i:i + chunk]) for i in range(0, len(pts), chunk)]
        shape = (resolution,) * 3
        out = {k: torch.cat([getattr(p, k).expand(-1, 3) for p in parts]).reshape(*shape, 3)
               for k in ("sigma_a", "sigma_s")}
        out["g"] = (torch.cat([p.g for p in parts]).reshape(shape) if self.phase != "none"
                    else torch.zeros(shape, device=pts.device))
        return out


class NeuralMedium(Medium):
    """The learned medium: the EA density modulated by a SIREN (or a grid)."""

    def __init__(self, effects: dict, density: nn.Module | None = None,
                 modulation: str = "siren", siren: dict | None = None,
                 grid_resolution: int = 32, init_albedo: float = 0.8):
        super().__init__(effects)
        if not 0.0 < init_albedo < 1.0:
            raise ValueError(f"model.medium.init_albedo must lie in (0, 1), got {init_albedo}")
        self.density_field = density
        n_out = 2 * self.channels + (self.phase == "field")
        if modulation == "siren":
            self.modulation: nn.Module = Siren(3, n_out, **(siren or {}))
        elif modulation == "grid":
            self.modulation = _GridModulation(grid_resolution, n_out)
        else:
            raise ValueError(f"model.medium.modulation must be 'siren' or 'grid', got "
                             f"'{modulation}'")
        self.g_shared = nn.Parameter(torch.zeros(())) if self.phase == "shared" else None
        offsets = [math.log(1 - init_albedo)] * self.channels + [math.log(init_albedo)] * \
            self.channels + [0.0] * (self.phase == "field")
        self.register_buffer("offsets", torch.tensor(offsets))

    def rho(self, x: torch.Tensor) -> torch.Tensor:
        """The density being modulated (...,): the EA field's, or 1 without a first stage."""
        if self.density_field is None:
            return torch.ones(x.shape[:-1], dtype=x.dtype, device=x.device)
        return self.density_field.density(x)

    def forward(self, x: torch.Tensor) -> MediumProperties:
        unit = (x - self.bbox[0]) / (self.bbox[1] - self.bbox[0]) * 2 - 1
        h = self.modulation(unit) + self.offsets
        c = self.channels
        a, s = h[..., :c].clamp(*EXPONENT_RANGE), h[..., c:2 * c].clamp(*EXPONENT_RANGE)
        rho = self.rho(x).unsqueeze(-1)
        if self.phase == "field":
            g = G_MAX * torch.tanh(h[..., 2 * c])
        elif self.phase == "shared":
            g = (G_MAX * torch.tanh(self.g_shared)).expand(x.shape[:-1])
        else:
            g = None
        return MediumProperties(rho * torch.exp(a), rho * torch.exp(s), torch.sigmoid(s - a), g)


class _GridModulation(nn.Module):
    """A dense trilinear grid of modulation values on [-1, 1]^3 (the paper's grid ablation)."""

    def __init__(self, resolution: int, n_out: int):
        super().__init__()
        self.values = nn.Parameter(torch.zeros(resolution, resolution, resolution, n_out))
        self.register_buffer("unit_box", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    def forward(self, unit: torch.Tensor) -> torch.Tensor:
        return sample_grid(self.values, unit, self.unit_box)


class GroundTruthMedium(Medium):
    """Trilinear lookups of ground-truth grids: ``sigma_a``, ``sigma_s`` (Nz, Ny, Nx, 3) and
    ``g`` (Nz, Ny, Nx), in the box ``bbox`` (2, 3). Nothing here is trained."""

    def __init__(self, effects: dict, sigma_a: torch.Tensor, sigma_s: torch.Tensor,
                 g: torch.Tensor, bbox: torch.Tensor):
        super().__init__(effects)
        c = self.channels
        stacked = torch.cat((sigma_a[..., :c], sigma_s[..., :c], g.unsqueeze(-1)), -1)
        self.register_buffer("stacked", stacked.float(), persistent=False)
        self.bbox.copy_(bbox)

    def forward(self, x: torch.Tensor) -> MediumProperties:
        v = sample_grid(self.stacked, x, self.bbox)
        c = self.channels
        sigma_a, sigma_s = v[..., :c].clamp_min(0.0), v[..., c:2 * c].clamp_min(0.0)
        sigma_t = sigma_a + sigma_s
        albedo = torch.where(sigma_t > 0, sigma_s / sigma_t.clamp_min(1e-30),
                             torch.zeros_like(sigma_t))
        g = v[..., 2 * c].clamp(-G_MAX, G_MAX) if self.phase != "none" else None
        return MediumProperties(sigma_a, sigma_s, albedo, g)
