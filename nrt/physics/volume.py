"""Rays through the medium box: intersection, grid lookup and transmittance.

Grids are arrays ``(Nz, Ny, Nx, C)`` indexed ``[z, y, x]`` whose values sit at cell
centres ``lo + (i + 0.5) * (hi - lo) / N``; lookups are trilinear and clamp to the edge
cells, exactly like Mitsuba's ``gridvolume`` (a Dr.Jit ``Texture3f``). Transmittance is
kept in log space (optical depth) and exponentiated once.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch.profiler import record_function

from nrt.physics import fused_lookup
from nrt.physics.compositing import stratified_samples


def ray_box_intersect(
    origins: torch.Tensor, dirs: torch.Tensor, bbox: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays with the box ``bbox = [[lo], [hi]]`` (2, 3).

    Returns ``(t_near, t_far, hit)``; ``t_near >= 0`` (origins inside start at 0) and
    ``hit`` is False where the ray misses or the box lies behind it. Axis-parallel rays
    are handled without dividing by zero.
    """
    tiny = torch.finfo(dirs.dtype).tiny
    safe = torch.where(dirs.abs() < tiny, torch.full_like(dirs, tiny), dirs)
    inv = 1.0 / safe
    t0 = (bbox[0] - origins) * inv
    t1 = (bbox[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far, t_far > t_near


def march(origins: torch.Tensor, dirs: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor,
          n_samples: int, jitter: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Points ``o + t d`` (N, n, 3) at ``n_samples`` strata of ``[t0, t1]`` (N,) along rays
    ``origins``, ``dirs`` (N, 3) (:func:`~nrt.physics.compositing.stratified_samples`), and
    the strata's lengths (N, n)."""
    t, delta = stratified_samples(t0, t1, n_samples, jitter)
    return origins.unsqueeze(1) + t.unsqueeze(-1) * dirs.unsqueeze(1), delta


def march_to_exit(points: torch.Tensor, dirs: torch.Tensor, bbox: torch.Tensor,
                  n_samples: int, jitter: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`march` from ``points`` (N, 3) inside the box along ``dirs`` to where each ray
    leaves ``bbox``."""
    with record_function("nrt/ray_marching"):  # a profiler scope (benchmarks.profile_step)
        _, t_exit, _ = ray_box_intersect(points, dirs, bbox)
        return march(points, dirs, torch.zeros_like(t_exit), t_exit, n_samples, jitter)


def cell_centres(resolution: int, bbox: torch.Tensor) -> torch.Tensor:
    """World positions (R, R, R, 3) of the box's grid cell centres, indexed ``[z, y, x]``."""
    axes = [bbox[0, a] + (torch.arange(resolution, dtype=bbox.dtype, device=bbox.device) + 0.5)
            / resolution * (bbox[1, a] - bbox[0, a]) for a in range(3)]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack((x, y, z), -1)


def at_cell_centres(fn: Callable[[torch.Tensor], torch.Tensor], resolution: int,
                    bbox: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
    """``fn(points (N, 3)) -> (N, ...)`` at the centres of ``resolution``^3 cells of ``bbox``
    (:func:`cell_centres`), ``chunk`` points at a time: (R, R, R, ...), ``[z, y, x]``."""
    pts = cell_centres(resolution, bbox).reshape(-1, 3)
    out = torch.cat([fn(pts[i:i + chunk]) for i in range(0, len(pts), chunk)])
    return out.reshape(resolution, resolution, resolution, *out.shape[1:])


SPLIT_LOOKUPS_FROM = 4096
"""Lookups of at least this many points on the CPU are split into one batch per thread:
torch's 3D ``grid_sample`` runs its batches in parallel, but each batch on one thread."""


def lookup_batches(points: int, device: torch.device) -> int:
    """Batches a CPU lookup of ``points`` points is split into: the largest divisor of
    ``points`` among 1 .. ``torch.get_num_threads()`` (1 on other devices and for small
    lookups). Values do not depend on it; gradients of the grid are summed over the
    batches, so their float rounding does."""
    if device.type != "cpu" or points < SPLIT_LOOKUPS_FROM:
        return 1
    return math.gcd(points, torch.get_num_threads())


def sample_grid(grid: torch.Tensor, points: torch.Tensor, bbox: torch.Tensor) -> torch.Tensor:
    """Trilinear, cell-centred, edge-clamped lookup of ``grid`` (Nz, Ny, Nx, C) at world
    ``points`` (..., 3) in the box ``bbox`` (2, 3). Returns (..., C). With
    ``fused_lookups=true`` on the CPU, one fused C++ pass (:mod:`nrt.physics.fused_lookup`)."""
    lead, c = points.shape[:-1], grid.shape[-1]
    if fused_lookup.fusable(grid, points, bbox):
        out = fused_lookup.fused_sample(grid, points.reshape(-1, 3), bbox)
        if out is not None:
            return out.reshape(*lead, c)
    unit = (points - bbox[0]) / (bbox[1] - bbox[0]) * 2 - 1  # [-1, 1], x first as grid_sample wants
    batches = lookup_batches(unit.numel() // 3, points.device)
    vol = grid.permute(3, 0, 1, 2).unsqueeze(0).to(points.dtype)
    out = F.grid_sample(
        vol.expand(batches, -1, -1, -1, -1), unit.reshape(batches, -1, 1, 1, 3),
        mode="bilinear", padding_mode="border", align_corners=False,
    )  # (batches, C, n / batches, 1, 1)
    return out.reshape(batches, c, -1).transpose(1, 2).reshape(*lead, c)


class GridExtinction:
    """Extinction read from a grid: ``sigma_t(points (..., 3)) -> (..., C)``, the
    :func:`sample_grid` lookup of ``grid`` (Nz, Ny, Nx, C) in ``bbox``; :func:`optical_depth`
    marches it in one fused pass where the fused kernels apply."""

    def __init__(self, grid: torch.Tensor, bbox: torch.Tensor):
        self.grid, self.bbox = grid, bbox

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        with record_function("nrt/medium"):  # a profiler scope (benchmarks.profile_step)
            return sample_grid(self.grid, points, self.bbox)


def optical_depth(
    sigma_t, origins: torch.Tensor, dirs: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor,
    n_samples: int, jitter: bool = False,
) -> torch.Tensor:
    """Optical depth ``int_t0^t1 sigma_t(o + t d) dt`` along each ray by the midpoint rule,
    or with ``jitter`` by ``n_samples`` equal strata shifted by one uniform offset per ray
    (an unbiased estimate of the depth that does not alias with a grid's cells).

    ``sigma_t`` maps points (..., 3) to extinction (..., C); returns (..., C). Segments
    with ``t1 <= t0`` give 0. A :class:`GridExtinction` is marched by one fused kernel
    where :func:`~nrt.physics.fused_lookup.fusable` (the same random offsets; the depth equal
    to float rounding).
    """
    with record_function("nrt/ray_marching"):
        length = (t1 - t0).clamp_min(0.0)
        offset = (torch.rand(*t0.shape, 1, dtype=origins.dtype, device=origins.device)
                  if jitter else 0.5)
    if isinstance(sigma_t, GridExtinction) and not (
            (dirs.requires_grad or t0.requires_grad or t1.requires_grad)
            and torch.is_grad_enabled()) and \
            fused_lookup.fusable(sigma_t.grid, origins, sigma_t.bbox):
        depth = fused_depth(sigma_t, origins, dirs, t0, length, offset, n_samples)
        if depth is not None:
            return depth
    with record_function("nrt/ray_marching"):
        frac = (torch.arange(n_samples, dtype=origins.dtype, device=origins.device) + offset) \
            / n_samples
        t = t0.unsqueeze(-1) + length.unsqueeze(-1) * frac  # (..., S)
        pts = origins.unsqueeze(-2) + t.unsqueeze(-1) * dirs.unsqueeze(-2)  # (..., S, 3)
    return sigma_t(pts).mean(-2) * length.unsqueeze(-1)


def fused_depth(sigma_t: GridExtinction, origins: torch.Tensor, dirs: torch.Tensor,
                t0: torch.Tensor, length: torch.Tensor, offset: torch.Tensor | float,
                n_samples: int) -> torch.Tensor | None:
    """:func:`optical_depth`'s march by :func:`~nrt.physics.fused_lookup.fused_march`: the rays
    broadcast and flattened, (..., C); None where the extension cannot be built."""
    with record_function("nrt/medium"):  # a profiler scope (benchmarks.profile_step)
        origins, dirs = torch.broadcast_tensors(origins, dirs)
        lead = origins.shape[:-1]
        flat = [t.expand(lead).reshape(-1) for t in (t0, length)]
        off = (offset.squeeze(-1).expand(lead) if torch.is_tensor(offset)
               else torch.full(lead, offset, dtype=origins.dtype, device=origins.device))
        depth = fused_lookup.fused_march(sigma_t.grid, origins.reshape(-1, 3),
                                         dirs.reshape(-1, 3), *flat, off.reshape(-1),
                                         sigma_t.bbox, n_samples)
        return None if depth is None else depth.reshape(*lead, -1)


def transmittance(tau: torch.Tensor) -> torch.Tensor:
    """``exp(-tau)`` of a non-negative optical depth (never overflows)."""
    return torch.exp(-tau.clamp_min(0.0))


def resample_cells(grid: torch.Tensor, resolution: int) -> torch.Tensor:
    """Trilinear, cell-centred, edge-clamped resampling of a grid (R, R, R, C) to
    ``resolution``^3 cells (the lookup of :func:`sample_grid` at the new cell centres)."""
    vol = grid.permute(3, 0, 1, 2).unsqueeze(0)
    out = F.interpolate(vol, size=(resolution,) * 3, mode="trilinear", align_corners=False)
    return out[0].permute(1, 2, 3, 0).contiguous()
