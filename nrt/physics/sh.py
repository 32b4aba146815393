"""Real spherical harmonics and the phase function's action on them.

``Y_lm`` (l = 0..degree, m = -l..l) are orthonormal on the unit sphere,
``int Y_lm Y_l'm' dw = delta``; band ``l`` holds ``2l + 1`` functions and a basis up to
``degree`` has ``(degree + 1)^2``, ordered ``(l, m) = (0, 0), (1, -1), (1, 0), (1, 1), ...``.
They are evaluated from Cartesian unit vectors by the usual recurrences (no angles):
``(x + i y)^m`` for the azimuth and the associated Legendre recurrence in ``z``, with the
Condon-Shortley phase ``(-1)^m`` (:func:`condon_shortley_signs` removes it).

Henyey-Greenstein's Legendre coefficients are ``g^l`` (Funk-Hecke), so for radiance
``L(w') = sum c_lm Y_lm(w')`` the in-scattered radiance is exact and needs no sampling:
``int f(w . w') L(w') dw' = sum g^l c_lm Y_lm(w)`` (:func:`phase_band_factors`). An
isotropic phase keeps only band 0.
"""

from __future__ import annotations

import math

import torch


def num_coefficients(degree: int) -> int:
    """``(degree + 1)^2`` basis functions up to ``degree``."""
    return (degree + 1) ** 2


def band_of_coefficient(degree: int) -> torch.Tensor:
    """Band ``l`` (long, ``((degree + 1)^2,)``) of every coefficient in basis order."""
    return torch.cat([torch.full((2 * band + 1,), band, dtype=torch.long)
                      for band in range(degree + 1)])


def condon_shortley_signs(degree: int) -> torch.Tensor:
    """``(-1)^m`` (float, ``((degree + 1)^2,)``) of every coefficient in basis order.

    :func:`sh_basis` carries the Condon-Shortley phase (``Y_1,1 = -sqrt(3 / 4 pi) x``);
    multiplied by these signs it is the real basis without it, graphics' usual table
    (``Y_1,1 = +sqrt(3 / 4 pi) x``), which the EA field's colour network reads."""
    return torch.tensor([(-1.0) ** abs(m) for band in range(degree + 1)
                         for m in range(-band, band + 1)])


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH ``Y_lm(d)`` (..., (degree + 1)^2) of unit directions ``d`` (..., 3)."""
    if degree < 0:
        raise ValueError(f"SH degree must be >= 0, got {degree}")
    x, y, z = d.unbind(-1)
    out: list[list[torch.Tensor | None]] = [[None] * (2 * band + 1)
                                            for band in range(degree + 1)]
    cos_m, sin_m = torch.ones_like(x), torch.zeros_like(x)  # Re, Im of (x + i y)^m
    double_factorial = 1.0  # (2m - 1)!!
    for m in range(degree + 1):
        if m > 0:
            cos_m, sin_m = cos_m * x - sin_m * y, cos_m * y + sin_m * x
            double_factorial *= 2 * m - 1
        q_prev = torch.full_like(z, (-1) ** m * double_factorial)  # Q_m^m (P_m^m / sin^m)
        q_prev2 = None
        for n in range(m, degree + 1):
            if n == m:
                q = q_prev
            elif n == m + 1:
                q = z * (2 * m + 1) * q_prev
            else:
                q = ((2 * n - 1) * z * q_prev - (n + m - 1) * q_prev2) / (n - m)
            if n > m:
                q_prev2, q_prev = q_prev, q
            k = math.sqrt((2 * n + 1) / (4 * math.pi) * math.factorial(n - m)
                          / math.factorial(n + m))
            if m == 0:
                out[n][n] = k * q
            else:
                out[n][n + m] = math.sqrt(2) * k * q * cos_m
                out[n][n - m] = math.sqrt(2) * k * q * sin_m
    return torch.stack([f for band in out for f in band], -1)


def phase_band_factors(g: torch.Tensor | None, degree: int) -> torch.Tensor:
    """Per-coefficient factors (..., (degree + 1)^2) of the phase convolution: ``g^l`` for
    HG (``g`` (...,)), and ``[1, 0, 0, ...]`` for an isotropic phase (``g`` None)."""
    bands = band_of_coefficient(degree)
    if g is None:
        return (bands == 0).float()
    bands = bands.to(g.device)
    return g.unsqueeze(-1) ** bands.to(g.dtype)
