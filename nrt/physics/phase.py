"""Henyey-Greenstein phase function, in directions of travel.

``f(w, w') = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5)`` with ``cos = w . w'``, where
``w`` is the direction light travels before scattering and ``w'`` after; ``g > 0`` scatters
forward. Mitsuba's ``hg`` passes the incoming direction pointing *back* (``mi.wi = -w``)
and so writes ``+2 g cos``; the same ``g`` means the same lobe in both, which a rendering
test pins. ``|g|`` is bounded by :data:`G_MAX`.
"""

from __future__ import annotations

import math

import torch

G_MAX = 0.95
"""Largest admissible ``|g|``; the medium field maps ``g = G_MAX * tanh(h)``."""

_G_EPS = 1e-2
"""Below this ``|g|`` the sampler uses the Taylor series of the HG inversion in ``g`` (the
closed form divides by ``g`` and loses digits to cancellation as ``g -> 0``)."""


def shared_g(sigma_s: torch.Tensor, g: torch.Tensor) -> float:
    """The one HG ``g`` standing for a grid of them: their mean weighted by the scattering
    coefficient ``sigma_s`` (..., C) averaged over its channels (in its own precision, then
    summed in float64, as the datasets' Mitsuba scenes have always been built), the plain
    mean of ``g`` (...) where nothing scatters."""
    weight = torch.as_tensor(sigma_s).mean(-1).double()
    g = torch.as_tensor(g).double()
    total = weight.sum()
    return float((weight * g).sum() / total) if total > 0 else float(g.mean())


def isotropic_phase(cos: torch.Tensor) -> torch.Tensor:
    """``1 / (4 pi)`` for every pair of directions, shaped like ``cos``."""
    return torch.full_like(cos, 1.0 / (4 * math.pi))


def hg_phase(cos: torch.Tensor, g: torch.Tensor | float) -> torch.Tensor:
    """HG density per steradian for ``cos = w . w'`` (directions of travel)."""
    g = torch.as_tensor(g, dtype=cos.dtype, device=cos.device)
    denom = (1 + g * g - 2 * g * cos).clamp_min(1e-12)
    return (1 - g * g) / (4 * math.pi * denom * torch.sqrt(denom))


def sample_hg_cos(g: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """Cosine between travel directions drawn from HG(g) by inversion, ``xi ~ U[0, 1)``.

    For ``|g| >= 1e-2`` the closed form ``(1 + g^2 - s^2) / (2 g)``, ``s = (1 - g^2) /
    (1 - g + 2 g xi)``; below, its Taylor series in ``g`` to second order,
    ``a + g (1 - a^2) (3/2 - 2 g a)`` with ``a = 2 xi - 1`` (the closed form's limit; the
    next term is below 1e-6 there). Both branches map ``xi`` the same way, so a sample
    moves continuously with ``g`` and its reparameterisation gradient ``d cos / d g`` is
    right at ``g = 0`` too (``3/2 (1 - a^2)``, not 0); the closed-form branch sees a safe
    ``g``, so neither ``torch.where`` branch produces a NaN that could reach a gradient.
    """
    g = torch.as_tensor(g, dtype=xi.dtype, device=xi.device)
    small = g.abs() < _G_EPS
    g_safe = torch.where(small, torch.full_like(g, _G_EPS), g)
    s = (1 - g_safe * g_safe) / (1 - g_safe + 2 * g_safe * xi)
    cos_hg = (1 + g_safe * g_safe - s * s) / (2 * g_safe)
    a = 2 * xi - 1
    cos_series = a + g * (1 - a * a) * (1.5 - 2 * g * a)
    return torch.where(small, cos_series, cos_hg).clamp(-1.0, 1.0)


def orthonormal_basis(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors completing unit ``n`` (..., 3) to a right-handed frame (Duff et al.)."""
    sign = torch.where(n[..., 2] >= 0, torch.ones_like(n[..., 2]), -torch.ones_like(n[..., 2]))
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = torch.stack((1 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]), -1)
    s = torch.stack((b, sign + n[..., 1] ** 2 * a, -n[..., 1]), -1)
    return t, s


def sample_hg(w: torch.Tensor, g: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """Scattered directions (..., 3) for incoming travel directions ``w`` under HG(g).

    ``xi`` (..., 2) are uniform samples; the density of the result is :func:`hg_phase`.
    """
    cos = sample_hg_cos(g, xi[..., 0])
    sin = torch.sqrt((1 - cos * cos).clamp_min(0.0))
    phi = 2 * math.pi * xi[..., 1]
    t, s = orthonormal_basis(w)
    return (
        (sin * torch.cos(phi)).unsqueeze(-1) * t
        + (sin * torch.sin(phi)).unsqueeze(-1) * s
        + cos.unsqueeze(-1) * w
    )


def sample_uniform_sphere(xi: torch.Tensor) -> torch.Tensor:
    """Unit directions (..., 3) uniform on the sphere from uniform ``xi`` (..., 2)."""
    cos = 1 - 2 * xi[..., 0]
    sin = torch.sqrt((1 - cos * cos).clamp_min(0.0))
    phi = 2 * math.pi * xi[..., 1]
    return torch.stack((sin * torch.cos(phi), sin * torch.sin(phi), cos), -1)


def sample_phase(w: torch.Tensor, g: torch.Tensor | None, xi: torch.Tensor) -> torch.Tensor:
    """Directions (..., 3) drawn from the phase function around travel directions ``w``:
    uniform on the sphere when ``g`` is None (isotropic), HG(g) otherwise. Either way the
    sample's weight ``f / pdf`` is exactly 1, so ``S = mean_k L(x, w'_k)``."""
    if g is None:
        return sample_uniform_sphere(xi)
    return sample_hg(w, g, xi)
