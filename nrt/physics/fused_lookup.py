"""Fused CPU kernels of :func:`~nrt.physics.volume.sample_grid` (``fused_lookups=true``): the
trilinear lookup of a channels-last grid at world points, and its gradient with respect to
the grid, in one C++ pass each (``csrc/grid_lookup.cpp``, built at first use by
:class:`nrt.compile.LazyExtension` and cached per machine). The values are the PyTorch
path's bit for bit; the grid's gradient sums in another order (a fixed number of partial
sums set by the sizes alone, so the same bits on any thread count). There is no gradient
with respect to the points: :func:`~nrt.physics.volume.sample_grid` takes the PyTorch path
where one is needed, on other devices, and where the extension cannot be built (one warning
per process says why).

:func:`fused_march` is :func:`~nrt.physics.volume.optical_depth` through a grid in one pass:
the strata's points and values are never stored (a shadow ray's march otherwise allocates
both, rays x strata x 3 and x C); each lookup is the PyTorch path's, the strata's mean sums
in order (equal to the PyTorch path's to float rounding).

The switch is process-wide (:func:`use_fused_lookups`, set by the ``fused_lookups``
callback of nrt-train), like torch's own backend flags: every lookup of a run goes the same
way.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from nrt.compile import LazyExtension

log = logging.getLogger(__name__)

EXTENSION = LazyExtension("nrt_grid_lookup_cpu", (Path(__file__).with_name("csrc") /
                                                  "grid_lookup.cpp",),
                          "fused_lookups: the fused CPU grid lookup", log)
"""The kernels, built at first use."""

_ENABLED = [False]
"""Whether :func:`~nrt.physics.volume.sample_grid` uses the kernels where they apply."""


def use_fused_lookups(enabled: bool) -> None:
    """Switch the fused kernels on or off for every later lookup of this process."""
    _ENABLED[0] = bool(enabled)


def fused_lookups() -> bool:
    """Whether the fused kernels are switched on (:func:`use_fused_lookups`)."""
    return _ENABLED[0]


def fusable(grid: torch.Tensor, points: torch.Tensor, bbox: torch.Tensor) -> bool:
    """Whether the fused kernels compute this lookup: switched on, CPU tensors, float32 or
    float64 points with a box of their dtype (the PyTorch path forms the box's extent in
    the box's dtype), no gradient needed with respect to the points or the box."""
    return (_ENABLED[0] and points.device.type == grid.device.type == bbox.device.type == "cpu"
            and points.dtype in (torch.float32, torch.float64) and bbox.dtype == points.dtype
            and not ((points.requires_grad or bbox.requires_grad)
                     and torch.is_grad_enabled()))


class FusedLookup(torch.autograd.Function):
    """``(grid (Nz, Ny, Nx, C), points (P, 3), bbox (2, 3)) -> (P, C)``, all of one dtype;
    differentiable in the grid only."""

    @staticmethod
    def forward(ctx, grid: torch.Tensor, points: torch.Tensor, bbox: torch.Tensor
                ) -> torch.Tensor:
        ctx.save_for_backward(points, bbox)
        ctx.shape = tuple(grid.shape)
        return EXTENSION.get().forward(grid, points, bbox)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, None, None]:
        if not ctx.needs_input_grad[0]:
            return None, None, None
        points, bbox = ctx.saved_tensors
        return EXTENSION.get().backward(grad.contiguous(), points, bbox, list(ctx.shape)), \
            None, None


@torch.compiler.disable  # an opaque C++ call: compiled code runs it eagerly
def fused_sample(grid: torch.Tensor, points: torch.Tensor, bbox: torch.Tensor
                 ) -> torch.Tensor | None:
    """The lookup (P, C) of ``grid`` (Nz, Ny, Nx, C) at ``points`` (P, 3) in ``bbox``
    (of the points' dtype), the grid cast to the points' dtype, or None where the extension
    cannot be built (the caller takes the PyTorch path)."""
    if EXTENSION.get() is None:
        return None
    dtype = points.dtype
    return FusedLookup.apply(grid.to(dtype).contiguous(), points.contiguous(),
                             bbox.contiguous())


class FusedMarch(torch.autograd.Function):
    """``(grid (Nz, Ny, Nx, C), origins (N, 3), dirs (N, 3), t0, length, offset (N,), bbox
    (2, 3), strata) -> (N, C)``, optical depths, all of one dtype; differentiable in the
    grid only."""

    @staticmethod
    def forward(ctx, grid: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                t0: torch.Tensor, length: torch.Tensor, offset: torch.Tensor,
                bbox: torch.Tensor, strata: int) -> torch.Tensor:
        ctx.save_for_backward(origins, dirs, t0, length, offset, bbox)
        ctx.shape, ctx.strata = tuple(grid.shape), strata
        return EXTENSION.get().march_forward(grid, origins, dirs, t0, length, offset, bbox,
                                             strata)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        none = (None,) * 7
        if not ctx.needs_input_grad[0]:
            return (None, *none)
        return (EXTENSION.get().march_backward(grad.contiguous(), *ctx.saved_tensors,
                                               ctx.strata, list(ctx.shape)), *none)


@torch.compiler.disable  # an opaque C++ call: compiled code runs it eagerly
def fused_march(grid: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                t0: torch.Tensor, length: torch.Tensor, offset: torch.Tensor,
                bbox: torch.Tensor, strata: int) -> torch.Tensor | None:
    """Optical depths (N, C) of rays ``origins``, ``dirs`` (N, 3) from ``t0`` over
    ``length`` (N,), ``strata`` strata shifted by ``offset`` (N,) in [0, 1), through
    ``grid`` (Nz, Ny, Nx, C) in ``bbox`` (all cast to the origins' dtype), or None where
    the extension cannot be built (the caller takes the PyTorch path)."""
    if EXTENSION.get() is None:
        return None
    dtype = origins.dtype
    return FusedMarch.apply(grid.to(dtype).contiguous(),
                            *(t.to(dtype).contiguous() for t in (origins, dirs, t0, length,
                                                                 offset, bbox)), int(strata))
