"""Shared references of the physics tests: a float64 box, an equal-weight quadrature of the
sphere, a sky with a sun-like spot and a homogeneous chromatic medium filling the box."""

from __future__ import annotations

import math

import torch

from nrt.modules.fields.medium import GroundTruthMedium
from nrt.physics.envmap import EnvironmentMap
from tests.mitsuba.test_mitsuba_physics import smooth_sky

BOX = torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64)


def fibonacci_sphere(n: int) -> torch.Tensor:
    """``n`` nearly uniform unit directions (n, 3), float64: an equal-weight quadrature
    rule (weight 4 pi / n) whose error on smooth integrands falls like 1/n."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), -1)


QUAD = fibonacci_sphere(400_000)


def bright_spot_sky(height: int = 16, width: int = 32) -> EnvironmentMap:
    """The smooth test sky plus a 200x brighter texel (a sun-like spot left in the sky)."""
    sky = torch.from_numpy(smooth_sky(height, width)).double()
    sky[5, 9] *= 200.0
    return EnvironmentMap(sky)


def homogeneous(sigma_a, sigma_s, g: float | None, n: int = 4) -> GroundTruthMedium:
    """A homogeneous chromatic medium filling :data:`BOX` (float64)."""
    phase = "isotropic" if g is None else "hg"
    shape = (n, n, n, 3)
    return GroundTruthMedium({"phase": phase, "chromatic": True},
                             torch.tensor(sigma_a).expand(shape),
                             torch.tensor(sigma_s).expand(shape),
                             torch.full((n, n, n), 0.0 if g is None else g), BOX).double()
