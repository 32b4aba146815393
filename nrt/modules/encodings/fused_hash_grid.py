"""Fused CPU kernels of :class:`~nrt.modules.encodings.hash_grid.HashGrid` (``fused=True``):
the encoding and its gradient with respect to the table in one C++ pass each
(``csrc/hash_grid.cpp``, built at first use by :func:`nrt.compile.load_extension` and cached
per machine), with the PyTorch path's arithmetic. The forward runs in parallel over points,
the backward over levels, on ATen's thread pool (``torch.set_num_threads``); both give the
same bits for any thread count. There is no gradient with respect to the points:
:meth:`HashGrid.forward` takes the PyTorch path where one is needed, on other devices, and
where the extension cannot be built (one warning per process says why).
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

import torch
from torch.autograd.function import once_differentiable

from nrt.compile import LazyExtension

log = logging.getLogger(__name__)

SOURCES = (Path(__file__).with_name("csrc") / "hash_grid.cpp",)
NAME = "nrt_hash_grid_cpu"

EXTENSION = LazyExtension(NAME, SOURCES, "hash_grid.fused: the fused CPU hash grid", log)
"""The kernels, built at first use."""


def extension() -> ModuleType | None:
    """The built extension, or None where it cannot be built (warned once per process;
    :func:`unavailable` says why)."""
    return EXTENSION.get()


def unavailable() -> str | None:
    """Why :func:`extension` could not build the extension; None where it could (or has
    not tried yet)."""
    return EXTENSION.unavailable()


class FusedEncoding(torch.autograd.Function):
    """``(x (P, 3), table (R, F)) -> (P, levels * F)``; differentiable in the table only.
    ``levels`` is ``(resolutions, offsets, dense, table_size)`` as HashGrid holds them."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, table: torch.Tensor, levels: tuple) -> torch.Tensor:
        ext = extension()
        ctx.save_for_backward(x)
        ctx.levels, ctx.rows = levels, table.shape[0]
        return ext.forward(x, table.contiguous(), *levels)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[None, torch.Tensor | None, None]:
        if not ctx.needs_input_grad[1]:
            return None, None, None
        (x,) = ctx.saved_tensors
        return None, extension().backward(grad.contiguous(), x, ctx.rows, *ctx.levels), None


def fusable(x: torch.Tensor, table: torch.Tensor) -> bool:
    """Whether the fused kernels compute this call: CPU tensors of one floating dtype
    (float32 or float64), no gradient needed with respect to ``x``."""
    return (x.device.type == "cpu" and table.device.type == "cpu"
            and x.dtype == table.dtype and x.dtype in (torch.float32, torch.float64)
            and not (x.requires_grad and torch.is_grad_enabled()))


@torch.compiler.disable  # an opaque C++ call: a compiled field runs it eagerly
def fused_encode(x: torch.Tensor, table: torch.Tensor, levels: tuple) -> torch.Tensor | None:
    """The encoding (P, levels * F) of points ``x`` (P, 3), or None where the extension
    cannot be built (the caller takes the PyTorch path)."""
    if extension() is None:
        return None
    return FusedEncoding.apply(x.contiguous(), table, levels)
