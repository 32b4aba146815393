"""The environment sampler: its density integrates to one, and it estimates a sky's integral
without bias.

Monte Carlo estimates are compared with z-scores: the estimate's standard error comes from
its own independent repetitions, and |z| < 5 fails by chance with probability < 1e-6."""

from __future__ import annotations

import math

import pytest
import torch

from nrt.physics.envmap import EnvironmentDirectionSampler
from tests.physics.homogeneous_box import QUAD, bright_spot_sky

pytestmark = pytest.mark.unit


def test_environment_sampler_density_is_normalised_and_unbiased():
    """The sampler's density integrates to 1 over the sphere (quadrature; the density is
    piecewise constant, so the rule's error is that of cell boundaries, ~1e-3 at 4e5
    points), and ``E(d) / pdf(d)`` over its samples estimates ``int E`` without bias:
    |z| < 5 against the quadrature of the bilinear lookup (whose own error, ~2e-4
    relative here, is below the estimate's standard error)."""
    env = bright_spot_sky()
    sampler = EnvironmentDirectionSampler(env)
    assert float(sampler.pdf(QUAD).mean() * 4 * math.pi) == pytest.approx(1.0, abs=3e-3)
    exact = env.lookup(QUAD).mean(0) * 4 * math.pi
    torch.manual_seed(3)
    d = sampler.sample(400_000).double()
    est = env.lookup(d) / sampler.pdf(d).unsqueeze(-1)
    z = (est.mean(0) - exact) / (est.std(0) / math.sqrt(len(d)))
    assert z.abs().max() < 5, z
