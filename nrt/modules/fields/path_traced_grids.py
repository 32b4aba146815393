"""The baseline's medium: voxel grids that Mitsuba path-traces, under a parametrisation.

:class:`PathTracedGrids` holds the optimised torch parameters and composes from them, with
autograd, the arrays Mitsuba's ``heterogeneous`` medium reads: ``sigma_t`` (R, R, R, C),
C = 3, or 1 when grey; ``albedo`` (R, R, R, 3); and for a learned g, ``g`` (R, R, R, 1)
for a g field or (1, 1, 1, 1) for one shared g (read through the ``nrt_hg_grid`` phase,
:mod:`nrt.mitsuba.hg_grid_phase`). The stage renders those arrays, gets Mitsuba's
gradients with respect to them and back-propagates them through :meth:`values` to the
parameters. Units: sigma per unit world length; g in [-G_MAX, G_MAX].

Parametrisations (``parametrization``):

- ``linear``: the grids are the parameters, clamped after each step (``0 <= sigma_t <=
  max_sigma_t``, albedo in [0, 1], |g| <= G_MAX): Mitsuba 3's volume-optimisation tutorial.
- ``log``: ``sigma_t = exp(u)``, ``albedo = sigmoid(b)``, ``g = G_MAX tanh(h)``: positive
  without clamps, steps relative to the value.
- ``modulated``: stage 2's medium (:class:`~nrt.modules.fields.voxel_medium.VoxelMedium`):
  ``sigma_t = rho exp(u)`` with ``rho`` the start's extinction, fixed on its
  ``start_resolution``^3 cells, and ``u`` (zero at the start), the albedo logits and g on
  the coarser grid that doubles; the arrays are composed on the finer of the two grids.

Every grid is cell-centred, ``[z, y, x]``, and doubles by trilinear resampling
(:mod:`nrt.modules.fields.coarse_to_fine`).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from nrt.errors import ConfigError
from nrt.modules.fields.coarse_to_fine import resample_parameter
from nrt.physics.phase import G_MAX
from nrt.physics.volume import resample_cells

PARAMETRIZATIONS = ("linear", "log", "modulated")
SMALLEST_LOG_EXTINCTION = 1e-3
"""``log``: cells of the start below this extinction (per unit length) start at it (log 0
is -inf)."""
LOGIT_LIMIT = 6.0
"""Albedo logits and g's pre-tanh start within +-6 (albedo 0.0025-0.9975)."""


def _resized(grid: torch.Tensor, resolution: int) -> torch.Tensor:
    return grid if grid.shape[0] == resolution else resample_cells(grid, resolution)


class PathTracedGrids(nn.Module):
    """Grids of sigma_t, albedo and (``g_kind`` ``shared`` or ``field``) g, on
    ``resolution``^3 cells under ``parametrization``; ``g_kind`` ``none`` (isotropic) or
    ``fixed`` (a given g, :attr:`fixed_g`) has no g parameter."""

    def __init__(self, channels: int, resolution: int, g_kind: str,
                 parametrization: str = "linear", start_resolution: int | None = None,
                 max_sigma_t: float = 100.0):
        super().__init__()
        if parametrization not in PARAMETRIZATIONS:
            raise ConfigError(f"model.parametrization='{parametrization}': the baseline's grids "
                              f"are one of {list(PARAMETRIZATIONS)}.")
        self.parametrization, self.g_kind = parametrization, g_kind
        self.channels, self.max_sigma_t = int(channels), float(max_sigma_t)
        r = int(resolution)
        self.sigma_t = nn.Parameter(torch.ones(r, r, r, self.channels))
        self.albedo = nn.Parameter(torch.full((r, r, r, 3), 0.8))
        g_shape = {"shared": (1, 1, 1, 1), "field": (r, r, r, 1)}.get(g_kind)
        self.g = nn.Parameter(torch.zeros(g_shape)) if g_shape else None
        self.fixed_g = 0.0
        if parametrization == "modulated":
            s = int(start_resolution or r)
            self.register_buffer("base", torch.ones(s, s, s, self.channels))

    # ------------------------------------------------------------------ state
    def parameters_by_name(self) -> dict[str, nn.Parameter]:
        """The optimised grids: ``sigma_t``, ``albedo`` and ``g`` when learned."""
        out = {"sigma_t": self.sigma_t, "albedo": self.albedo}
        if self.g is not None:
            out["g"] = self.g
        return out

    @property
    def resolution(self) -> int:
        """Cells per axis of the optimised grids now."""
        return self.sigma_t.shape[0]

    @torch.no_grad()
    def start(self, sigma_t: torch.Tensor, albedo: torch.Tensor,
              g: torch.Tensor | None = None) -> None:
        """Set the grids from a start on any cells of the same box: ``sigma_t`` (S, S, S, C
        or 1), ``albedo`` (S, S, S, 3), ``g`` (S, S, S) or None (g = 0). ``modulated``
        keeps ``sigma_t`` itself as ``rho`` at its own ``start_resolution``."""
        r = self.resolution
        sigma_t = sigma_t.float().expand(*sigma_t.shape[:3], self.channels).clamp(
            0, self.max_sigma_t)
        albedo = _resized(albedo.float(), r).clamp(0, 1)
        g = torch.zeros(sigma_t.shape[:3]) if g is None else g.float().clamp(-G_MAX, G_MAX)
        if self.g_kind == "shared":
            g_cells = g.mean().reshape(1, 1, 1, 1)  # a start's g, where it has one g field
        else:
            g_cells = _resized(g.unsqueeze(-1), r)
        if self.parametrization == "linear":
            self.sigma_t.copy_(_resized(sigma_t, r))
            self.albedo.copy_(albedo)
            if self.g is not None:
                self.g.copy_(g_cells)
            return
        self.albedo.copy_(torch.logit(albedo, eps=1e-6).clamp(-LOGIT_LIMIT, LOGIT_LIMIT))
        if self.g is not None:
            self.g.copy_(torch.atanh(g_cells / G_MAX).clamp(-LOGIT_LIMIT, LOGIT_LIMIT))
        if self.parametrization == "log":
            self.sigma_t.copy_(torch.log(_resized(sigma_t, r).clamp_min(SMALLEST_LOG_EXTINCTION)))
        else:
            self.base = _resized(sigma_t, self.base.shape[0]).contiguous()
            self.sigma_t.zero_()

    def resize(self, resolution: int, optimizer: torch.optim.Optimizer | None) -> None:
        """Resample every optimised grid but a shared g to ``resolution``^3 cells, its
        optimizer state restarted."""
        for name, p in self.parameters_by_name().items():
            if not (name == "g" and self.g_kind == "shared"):
                resample_parameter(p, optimizer, resolution)

    @torch.no_grad()
    def clamp_(self) -> None:
        """``linear``: keep the grids in range after an optimizer step (the others are in
        range by construction)."""
        if self.parametrization != "linear":
            return
        self.sigma_t.clamp_(0.0, self.max_sigma_t)
        self.albedo.clamp_(0.0, 1.0)
        if self.g is not None:
            self.g.clamp_(-G_MAX, G_MAX)

    def resize_to_state(self, state: dict, prefix: str = "") -> None:
        """Give each grid the shape it has in a checkpoint's ``state`` before loading it."""
        with torch.no_grad():
            for name, p in self.parameters_by_name().items():
                saved = state.get(prefix + name)
                if saved is not None and saved.shape != p.shape:
                    p.data = torch.zeros_like(saved)
            saved = state.get(prefix + "base")
            if saved is not None and hasattr(self, "base"):
                self.base = torch.zeros_like(saved)

    # ----------------------------------------------------------------- values
    def values(self) -> dict[str, torch.Tensor]:
        """The arrays Mitsuba renders (differentiable in the parameters): ``sigma_t``,
        ``albedo`` and, for a learned g, ``g`` (module docstring)."""
        kind = self.parametrization
        if kind == "linear":
            out = {"sigma_t": self.sigma_t, "albedo": self.albedo}
            if self.g is not None:
                out["g"] = self.g
            return out
        r = self.resolution if kind == "log" else max(self.resolution, self.base.shape[0])
        log_limit = math.log(self.max_sigma_t)
        exponent = _resized(self.sigma_t, r).clamp(max=log_limit)
        sigma_t = torch.exp(exponent) if kind == "log" else (
            _resized(self.base, r) * torch.exp(exponent)).clamp(max=self.max_sigma_t)
        out = {"sigma_t": sigma_t, "albedo": torch.sigmoid(_resized(self.albedo, r))}
        if self.g is not None:
            h = self.g if self.g_kind == "shared" else _resized(self.g, r)
            out["g"] = G_MAX * torch.tanh(h)
        return out

    @torch.no_grad()
    def property_arrays(self) -> dict[str, torch.Tensor]:
        """The medium in the ground truth's layout: ``sigma_a``, ``sigma_s`` (R, R, R, 3) and
        ``g`` (R, R, R) on the cells of :meth:`values`."""
        v = self.values()
        albedo = v["albedo"].detach().float()
        sigma_t = v["sigma_t"].detach().float().expand_as(albedo)
        shape = albedo.shape[:3]
        if "g" in v:
            g = v["g"].detach().float()[..., 0].expand(shape)
        else:
            g = torch.full(shape, self.fixed_g)
        return {"sigma_a": (1 - albedo) * sigma_t, "sigma_s": albedo * sigma_t,
                "g": g.contiguous()}
