"""Fused CPU kernels of the environment map (``fused_lookups=true``): the bilinear lookup
:meth:`~nrt.physics.envmap.EnvironmentMap.lookup`, the sampler's density
:meth:`~nrt.physics.envmap.EnvironmentDirectionSampler.pdf` and its draws of look directions,
one C++ pass each (``csrc/envmap.cpp``, built at first use and cached per machine). The
PyTorch path is a chain of a dozen ops over every direction; the sky light's shadow rays
and the uncollided refresh look up, weigh and draw hundreds of thousands of directions a
step. The arithmetic is the PyTorch path's, op by op in the same dtype: the values agree to
the last bit of atan2 / acos. There is no gradient: a direction that needs one takes the
PyTorch path, as do other devices and a machine where the extension cannot be built (one
warning per process). The switch is :func:`~nrt.physics.fused_lookup.use_fused_lookups`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from nrt.compile import LazyExtension
from nrt.physics.fused_lookup import fused_lookups

log = logging.getLogger(__name__)

EXTENSION = LazyExtension("nrt_envmap_cpu", (Path(__file__).with_name("csrc") / "envmap.cpp",),
                          "fused_lookups: the fused CPU environment-map kernels", log)
"""The kernels, built at first use."""


def _extension(*tensors: torch.Tensor):
    """The built extension where it computes this call (switched on, CPU tensors, no
    gradient needed), else None."""
    if not fused_lookups() or any(t.device.type != "cpu" for t in tensors) or \
            (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)):
        return None
    return EXTENSION.get()


@torch.compiler.disable  # an opaque C++ call: compiled code runs it eagerly
def fused_env_lookup(radiance: torch.Tensor, d: torch.Tensor) -> torch.Tensor | None:
    """Radiance (..., 3) of the map ``radiance`` (H, W, 3) at look directions ``d`` (..., 3)
    (cast to the map's dtype), or None where the kernels do not apply."""
    ext = _extension(radiance, d)
    if ext is None:
        return None
    flat = d.to(radiance.dtype).reshape(-1, 3).contiguous()
    return ext.lookup(radiance.contiguous(), flat).reshape(*d.shape[:-1], 3)


@torch.compiler.disable
def fused_env_pdf(density: torch.Tensor, d: torch.Tensor) -> torch.Tensor | None:
    """Density (...,) per steradian of the cells of ``density`` (H, W) holding look
    directions ``d`` (..., 3), in ``d``'s dtype, or None where the kernels do not apply."""
    ext = _extension(density, d)
    if ext is None:
        return None
    return ext.pdf(density.contiguous(), d.reshape(-1, 3).contiguous()).reshape(d.shape[:-1])


@torch.compiler.disable
def fused_env_sample(cdf: torch.Tensor, cos_top: torch.Tensor, cos_bottom: torch.Tensor,
                     width: int, xi: torch.Tensor) -> torch.Tensor | None:
    """Look directions (N, 3), float32, from uniform numbers ``xi`` (N, 3) (float64) by the
    cumulative cell probabilities ``cdf`` (H W) and the rows' polar bounds ``cos_top``,
    ``cos_bottom`` (H,), or None where the kernels do not apply."""
    ext = _extension(xi)
    if ext is None:
        return None
    return ext.sample(cdf, cos_top, cos_bottom, int(width), xi.contiguous())
