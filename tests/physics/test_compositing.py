"""Alpha compositing and stratified sampling: analytic homogeneous slabs and hard cases."""

import math

import pytest
import torch

from nrt.physics.compositing import alpha_composite, stratified_samples

pytestmark = pytest.mark.unit


def test_homogeneous_slab_matches_closed_form():
    # Constant sigma and colour c over length D: I = c (1 - e^{-sigma D}) + e^{-sigma D} E,
    # exact for any number of samples (the alpha form integrates each segment exactly).
    sigma, length, c, e = 1.7, 2.0, torch.tensor([0.3, 0.6, 0.9]), torch.tensor([2.0, 1.0, 0.5])
    t, delta = stratified_samples(torch.zeros(1, dtype=torch.float64),
                                  torch.full((1,), length, dtype=torch.float64), 7, jitter=False)
    color, t_final = alpha_composite(torch.full_like(t, sigma), delta,
                                     c.double().expand(1, 7, 3), e.double()[None])
    trans = math.exp(-sigma * length)
    torch.testing.assert_close(t_final, torch.tensor([trans], dtype=torch.float64))
    torch.testing.assert_close(color[0], (c * (1 - trans) + e * trans).double())


def test_dense_and_near_empty_media_stay_finite_and_exact():
    t, delta = stratified_samples(torch.zeros(2), torch.full((2,), 2.0), 64, jitter=True)
    sigma = torch.stack((torch.full((64,), 1e4), torch.full((64,), 1e-8)))
    values = torch.ones(2, 64, 3, requires_grad=True)
    color, t_final = alpha_composite(sigma, delta, values, torch.zeros(2, 3))
    color.sum().backward()
    assert torch.isfinite(color).all() and torch.isfinite(values.grad).all()
    torch.testing.assert_close(color[0], torch.ones(3))  # opaque: the medium's own colour
    torch.testing.assert_close(color[1], torch.full((3,), 2e-8), rtol=1e-4, atol=0)


def test_stratified_samples_cover_each_stratum_once():
    t0, t1 = torch.tensor([0.5]), torch.tensor([2.5])
    t, delta = stratified_samples(t0, t1, 4, jitter=True)
    edges = torch.linspace(0.5, 2.5, 5)
    assert torch.all((t[0] >= edges[:-1]) & (t[0] < edges[1:]))
    torch.testing.assert_close(delta.sum(-1), t1 - t0)
