"""Spherical harmonics against quadrature: the basis is orthonormal, and the HG phase acts on
band l by g^l (Funk-Hecke)."""

from __future__ import annotations

import math

import pytest
import torch

from nrt.physics.phase import hg_phase
from nrt.physics.sh import num_coefficients, phase_band_factors, sh_basis
from tests.physics.homogeneous_box import QUAD

pytestmark = pytest.mark.unit


def test_sh_basis_is_orthonormal_and_hg_acts_by_g_to_the_band():
    """Gram matrix of the basis up to degree 4 by quadrature is the identity (the rule's
    error on degree-8 polynomials at 4e5 points is ~1e-6; bound 1e-4), and Funk-Hecke: the
    HG convolution of ``Y_lm`` is ``g^l Y_lm`` (bound 1e-4 absolute on values <= 1.3,
    the integrand being smooth for |g| <= 0.6), for both signs of g and for g = 0, where
    only band 0 survives, which is what the isotropic factors say."""
    y = sh_basis(QUAD, 4)
    assert y.shape == (len(QUAD), num_coefficients(4))
    gram = y.T @ y * (4 * math.pi / len(QUAD))
    torch.testing.assert_close(gram, torch.eye(25, dtype=torch.float64), rtol=0, atol=1e-4)
    w = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64))
    for g in (-0.6, 0.0, 0.35, 0.6):
        f = hg_phase(QUAD @ w[0], g)
        convolved = (f[:, None] * y).sum(0) * (4 * math.pi / len(QUAD))
        exact = phase_band_factors(torch.tensor(g, dtype=torch.float64), 4) * sh_basis(w, 4)[0]
        torch.testing.assert_close(convolved, exact, rtol=0, atol=1e-4)
    torch.testing.assert_close(phase_band_factors(None, 2),
                               torch.tensor([1.0] + [0.0] * 8))
