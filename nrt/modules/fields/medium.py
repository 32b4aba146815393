"""Media of stage 2: ``x -> (sigma_a, sigma_s, g)``, built for exactly the scene's effects.

Heads follow the scene's declared effects (docs/conventions.md, "Scene effects"):
``phase=isotropic`` has no g at all, ``phase=hg`` one shared learnable g,
``phase=varying_hg`` a g field. Extinction is RGB, or with ``chromatic=false`` grey: one
sigma_t channel with an RGB albedo, as the scene spec draws it, Mitsuba renders it (a
one-channel ``sigma_t`` grid, a three-channel ``albedo``) and ``stage=dpt`` fits it.
Units: sigma per unit world length; g in [-G_MAX, G_MAX].

- :class:`NeuralMedium`: chromatic (``parametrization=scattering``): ``sigma_a = rho(x)
  exp(a(x))``, ``sigma_s = rho(x) exp(s(x))`` per channel, ``albedo = sigmoid(s - a)``
  (exact without dividing by a small sigma_t); grey, or chromatic with
  ``parametrization=extinction``: ``sigma_t = rho(x) exp(t(x))`` (one channel, or three),
  ``albedo = sigmoid(b(x))`` (RGB), ``sigma_s = sigma_t albedo``, ``sigma_a = sigma_t (1 -
  albedo)``. Both:
  ``g = G_MAX tanh(h(x))``, with ``rho`` the EA density (or 1 without a first stage) and
  the exponents and logits from a modulation network: a SIREN (``model/medium=siren``) or,
  for the paper's ablation, a trilinear grid (:class:`GridModulation`, ``model/medium=grid``).
  Exponents are clamped so exp never overflows.
- :class:`GroundTruthMedium`: the dataset's grids (forward mode, tests); a grey one reads
  them as Mitsuba does: trilinear sigma_t (channel 0) and trilinear albedo.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn
from torch.profiler import record_function

from nrt.errors import ConfigError
from nrt.physics.phase import G_MAX
from nrt.physics.volume import at_cell_centres, sample_grid

PARAMETRIZATIONS = ("scattering", "extinction")
"""Chromatic media modulate ``(sigma_a, sigma_s)`` by exponents, or ``(sigma_t, albedo)`` by
an exponent and a logit per channel (grey media always use the second)."""

PHASE_HEADS = {"isotropic": "none", "hg": "shared", "varying_hg": "field"}
"""How each declared phase is represented: no g, one shared g, or a g field."""

EXPONENT_RANGE = (-15.0, 10.0)
"""Clamp of the exponents ``a, s``: exp stays within [3e-7, 2.2e4] times the density."""


@dataclass
class MediumProperties:
    """Optical properties at a batch of points: ``sigma_a``, ``sigma_s``, ``albedo`` =
    sigma_s / sigma_t (..., 3), ``g`` (...,) or None for an isotropic phase, and for grey
    media ``extinction``, the one sigma_t channel (..., 1) that broadcasts over RGB."""

    sigma_a: torch.Tensor
    sigma_s: torch.Tensor
    albedo: torch.Tensor
    g: torch.Tensor | None
    extinction: torch.Tensor | None = None

    @property
    def sigma_t(self) -> torch.Tensor:
        """(..., 3), or (..., 1) for grey media."""
        return self.extinction if self.extinction is not None else self.sigma_a + self.sigma_s


def scene_channels(effects: dict) -> int:
    """Channels of the extinction: 3 for chromatic scenes, 1 for grey ones (the albedo
    always has 3)."""
    return 3 if effects.get("chromatic", True) else 1


def phase_head(effects: dict) -> str:
    phase = effects.get("phase", "hg")
    if phase not in PHASE_HEADS:
        raise ConfigError(f"scene.effects.phase must be one of {sorted(PHASE_HEADS)}, "
                          f"got '{phase}'.")
    return PHASE_HEADS[phase]


class Medium(nn.Module):
    """Base of every medium: ``forward(x) -> MediumProperties`` at world points (..., 3)."""

    def __init__(self, effects: dict):
        super().__init__()
        self.channels = scene_channels(effects)
        self.phase = phase_head(effects)
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    def grids(self, resolution: int, chunk: int = 65536) -> dict[str, torch.Tensor]:
        """Properties at the box's cell centres (:func:`property_grids`)."""
        return property_grids(self, resolution, chunk)


@torch.no_grad()
def property_grids(medium, resolution: int, chunk: int = 65536) -> dict[str, torch.Tensor]:
    """A medium's properties at the cell centres of its box, ``[z, y, x]``-indexed like the
    dataset's ground truth: ``sigma_a``, ``sigma_s`` (R, R, R, 3) and ``g`` (R, R, R) (zero
    for an isotropic phase). ``medium(x) -> MediumProperties`` with ``bbox`` and ``phase``
    (a :class:`Medium`, or voxels composed from one)."""
    has_g = medium.phase != "none"

    def packed(x: torch.Tensor) -> torch.Tensor:
        p = medium(x)
        columns = [p.sigma_a.expand(-1, 3), p.sigma_s.expand(-1, 3)]
        return torch.cat(columns + [p.g.reshape(-1, 1)] if has_g else columns, -1)

    v = at_cell_centres(packed, resolution, medium.bbox, chunk)
    return {"sigma_a": v[..., :3].contiguous(), "sigma_s": v[..., 3:6].contiguous(),
            "g": (v[..., 6].contiguous() if has_g
                  else torch.zeros(v.shape[:3], device=v.device))}


class NeuralMedium(Medium):
    """The learned medium: the EA density modulated by a network. ``modulation(in_dim,
    out_dim)`` builds that network (a SIREN or a :class:`GridModulation`, as the config
    ``model/medium`` gives it) from unit-box points (3) to the exponents and logits."""

    def __init__(self, effects: dict, density: nn.Module | None = None,
                 modulation: Callable[[int, int], nn.Module] | None = None,
                 init_albedo: float = 0.8, parametrization: str = "scattering"):
        super().__init__(effects)
        if not callable(modulation):
            raise ConfigError(f"model.medium.modulation={modulation}: the modulation network "
                              "is a component chosen by config group: model/medium=siren or "
                              "model/medium=grid (conf/model/medium/).")
        if not 0.0 < init_albedo < 1.0:
            raise ConfigError(f"model.medium.init_albedo must lie in (0, 1), got "
                              f"{init_albedo}.")
        if parametrization not in PARAMETRIZATIONS:
            raise ConfigError(f"model.medium.parametrization must be one of "
                              f"{list(PARAMETRIZATIONS)}, got '{parametrization}'.")
        self.density_field = density
        # exponents a (3), s (3); or t (1 grey, 3 chromatic), albedo logits b (3); then h
        self.by_extinction = self.channels == 1 or parametrization == "extinction"
        self.g_index = self.channels + 3 if self.by_extinction else 6
        n_out = self.g_index + (self.phase == "field")
        self.modulation: nn.Module = modulation(3, n_out)
        self.g_shared = nn.Parameter(torch.zeros(())) if self.phase == "shared" else None
        # start: sigma_t = rho, albedo = init_albedo (a, s: exp(a) + exp(s) = 1)
        offsets = ([0.0] * self.channels + [math.log(init_albedo / (1 - init_albedo))] * 3
                   if self.by_extinction else
                   [math.log(1 - init_albedo)] * 3 + [math.log(init_albedo)] * 3)
        offsets += [0.0] * (self.phase == "field")
        self.register_buffer("offsets", torch.tensor(offsets))

    def rho(self, x: torch.Tensor) -> torch.Tensor:
        """The density being modulated (...,): the EA field's, or 1 without a first stage."""
        if self.density_field is None:
            return torch.ones(x.shape[:-1], dtype=x.dtype, device=x.device)
        return self.density_field.density(x)

    def forward(self, x: torch.Tensor) -> MediumProperties:
        with record_function("nrt/medium"):  # a profiler scope (benchmarks.profile_step)
            unit = (x - self.bbox[0]) / (self.bbox[1] - self.bbox[0]) * 2 - 1
            return self.heads(self.rho(x).unsqueeze(-1), self.modulation(unit) + self.offsets)

    def heads(self, rho: torch.Tensor, h: torch.Tensor,
              g_logit: torch.Tensor | None = None) -> MediumProperties:
        """Properties from the density ``rho`` (..., 1) and the raw outputs ``h`` (..., n)
        (exponents, logits and the g field's pre-activation, offsets included); a shared g's
        pre-activation ``g_logit`` (a scalar) in place of ``g_shared`` where given."""
        if self.phase == "field":
            g = G_MAX * torch.tanh(h[..., self.g_index])
        elif self.phase == "shared":
            logit = self.g_shared if g_logit is None else g_logit
            g = (G_MAX * torch.tanh(logit)).expand(h.shape[:-1])
        else:
            g = None
        if self.by_extinction:
            c = self.channels
            sigma_t = rho * torch.exp(h[..., :c].clamp(*EXPONENT_RANGE))
            b = h[..., c:c + 3]
            return MediumProperties(sigma_t * torch.sigmoid(-b), sigma_t * torch.sigmoid(b),
                                    torch.sigmoid(b), g,
                                    extinction=sigma_t if c == 1 else None)
        a, s = h[..., :3].clamp(*EXPONENT_RANGE), h[..., 3:6].clamp(*EXPONENT_RANGE)
        return MediumProperties(rho * torch.exp(a), rho * torch.exp(s), torch.sigmoid(s - a), g)


class GridModulation(nn.Module):
    """A dense trilinear grid of ``out_dim`` modulation values per cell on [-1, 1]^3 (the
    paper's grid ablation; the voxel medium's modulation), zeros at the start."""

    def __init__(self, in_dim: int, out_dim: int, resolution: int = 32):
        super().__init__()
        if in_dim != 3:
            raise ConfigError(f"a grid modulation takes 3-d points, got in_dim={in_dim}.")
        self.values = nn.Parameter(torch.zeros(resolution, resolution, resolution, out_dim))
        self.register_buffer("unit_box", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    def grids(self) -> list[nn.Parameter]:
        """The grid parameters a coarse-to-fine schedule resamples."""
        return [self.values]

    def forward(self, unit: torch.Tensor) -> torch.Tensor:
        return sample_grid(self.values, unit, self.unit_box)


class GroundTruthMedium(Medium):
    """Trilinear lookups of ground-truth grids: ``sigma_a``, ``sigma_s`` (Nz, Ny, Nx, 3) and
    ``g`` (Nz, Ny, Nx), in the box ``bbox`` (2, 3). Nothing here is trained.

    Chromatic media interpolate sigma_a and sigma_s; grey ones interpolate what Mitsuba's
    grids hold (:func:`nrt.mitsuba.scene.mitsuba_properties`): sigma_t of channel 0
    and the RGB albedo sigma_s / sigma_t (0 where sigma_t is 0)."""

    def __init__(self, effects: dict, sigma_a: torch.Tensor, sigma_s: torch.Tensor,
                 g: torch.Tensor, bbox: torch.Tensor):
        super().__init__(effects)
        if self.channels == 1:
            sigma_t = sigma_a + sigma_s
            sigma_a, sigma_s = sigma_t[..., :1], _albedo(sigma_s, sigma_t)  # slots: sigma_t, albedo
        stacked = torch.cat((sigma_a, sigma_s, g.unsqueeze(-1)), -1)
        self.register_buffer("stacked", stacked.float(), persistent=False)
        self.bbox.copy_(bbox)

    def forward(self, x: torch.Tensor) -> MediumProperties:
        with record_function("nrt/medium"):
            v = sample_grid(self.stacked, x, self.bbox)
            g = v[..., -1].clamp(-G_MAX, G_MAX) if self.phase != "none" else None
            if self.channels == 1:
                sigma_t, albedo = v[..., :1].clamp_min(0.0), v[..., 1:4].clamp(0.0, 1.0)
                return MediumProperties(sigma_t * (1 - albedo), sigma_t * albedo, albedo, g,
                                        extinction=sigma_t)
            sigma_a, sigma_s = v[..., :3].clamp_min(0.0), v[..., 3:6].clamp_min(0.0)
            return MediumProperties(sigma_a, sigma_s, _albedo(sigma_s, sigma_a + sigma_s), g)


def _albedo(sigma_s: torch.Tensor, sigma_t: torch.Tensor) -> torch.Tensor:
    """``sigma_s / sigma_t``, 0 where sigma_t is 0."""
    return torch.where(sigma_t > 0, sigma_s / sigma_t.clamp_min(1e-30), torch.zeros_like(sigma_t))
