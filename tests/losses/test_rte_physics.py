"""Physics unit tests of stage 2, each against a reference built independently of the code
under test: finite differences and ``torch.func.jvp`` for the light field's directional
derivative, the white furnace for the residual and the boundary loss, a deterministic
quadrature for the unbiased squared residual's gradient, the HG density for its sampler,
closed forms for the sun split and for the first scattering of known lights, and face
areas for the boundary sampler.

Monte Carlo tolerances are z-scores on standard errors measured from the samples
themselves (or chi-square quantiles); deterministic ones come from float rounding or the
quadrature's own, separately measured, error. Everything is seeded and runs in seconds.
"""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest
import torch
from scipy.stats import chi2, kstest

import nrt.losses.rte as rte_module
from nrt.losses.boundary import boundary_loss
from nrt.losses.rte import rte_loss, rte_residuals
from nrt.losses.samplers import (
    DensityPointSampler,
    EnvironmentDirectionSampler,
    boundary_samples,
    collocation_points,
    uniform_box_points,
)
from nrt.losses.unbiased import unbiased_square
from nrt.modules.encodings.siren import Siren
from nrt.modules.fields.light_field import LOG_RADIANCE_MAX, LightField
from nrt.modules.fields.medium import (
    EXPONENT_RANGE,
    GridModulation,
    GroundTruthMedium,
    NeuralMedium,
)
from nrt.physics.direct_light import DirectLights, direct_inscatter, split_sun
from nrt.physics.envmap import EnvironmentMap
from nrt.physics.inscatter import inscattered_radiance
from nrt.physics.phase import (
    G_MAX,
    hg_phase,
    sample_hg,
    sample_hg_cos,
    sample_phase,
)

pytestmark = pytest.mark.unit

CUBE = torch.tensor([[-1.0] * 3, [1.0] * 3])
SLAB = torch.tensor([[-2.0, -0.5, -1.0], [1.0, 0.5, 3.0]])
"""A non-cubic box (extents 3, 1, 4) with an off-centre origin: it catches code that
assumes [-1, 1]^3 (chain-rule factors, face areas, exit distances)."""


def unit_vectors(n: int, dtype=torch.float32, generator=None) -> torch.Tensor:
    """Unit vectors from normalised Gaussians (independent of the library's samplers)."""
    v = torch.randn(n, 3, dtype=dtype, generator=generator)
    return v / v.norm(dim=-1, keepdim=True)


def hg_reference(cos: torch.Tensor, g: float) -> torch.Tensor:
    """The HG formula (docs/conventions.md, "Phase function"), written out, not imported."""
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos) ** 1.5)


def box_exit_distance(x: torch.Tensor, d: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Distance from points ``x`` inside ``box`` along unit ``d`` to the box's boundary,
    axis by axis with Python floats (no component of ``d`` in the tests is zero)."""
    out = []
    for xi, di in zip(x.tolist(), d.tolist(), strict=True):
        ts = [((box[1, a] if di[a] > 0 else box[0, a]).item() - xi[a]) / di[a]
              for a in range(3)]
        out.append(min(ts))
    return torch.tensor(out, dtype=x.dtype)


# ----------------------------------------------------------------------------------------
# 1. Directional derivative of the light field
# ----------------------------------------------------------------------------------------


def test_directional_derivative_equals_finite_differences_and_jvp():
    """``with_derivative``'s second output is ``(w . grad_x) L``.

    float64 SIREN (hidden 32, 3 layers, omega 30) in the non-cubic box SLAB with
    ``radiance_scale`` 3.7, so the chain-rule factor ``2 / extent`` per axis and the scale
    both matter. Central differences with h = 1e-6 have truncation error
    ``h^2 |L'''| / 6`` and rounding error ``~eps |L| / h``; with |L'''| at most ~1e4 |L|
    for these frequencies both are ~1e-10 |L|, so ``rtol = 1e-6`` (plus ``atol = 1e-6``
    times the typical |derivative|, for entries that happen to cross zero) has a margin
    of ~1e4 and still catches any wrong factor. ``torch.func.jvp`` of ``forward`` computes
    the same product by a different route (dual numbers through the same ops), so it
    must agree to rounding: ``rtol = 1e-10``.
    """
    torch.manual_seed(10)
    light = LightField(hidden=32, layers=3, omega_0=30.0, omega_hidden=30.0).double()
    light.bbox.copy_(SLAB.double())
    light.radiance_scale.fill_(3.7)
    box = SLAB.double()
    x = box[0] + (0.05 + 0.9 * torch.rand(256, 3, dtype=torch.float64)) * (box[1] - box[0])
    w = unit_vectors(256, torch.float64)
    with torch.no_grad():
        value, deriv = light.with_derivative(x, w)
        torch.testing.assert_close(value, light(x, w), rtol=1e-13, atol=0)
        h = 1e-6
        fd = (light(x + h * w, w) - light(x - h * w, w)) / (2 * h)
    assert fd.abs().mean() > 0.1  # a non-trivial field: the comparison has teeth
    torch.testing.assert_close(deriv, fd, rtol=1e-6, atol=1e-6 * float(fd.abs().mean()))
    with torch.no_grad():
        _, jvp = torch.func.jvp(lambda p: light(p, w), (x,), (w,))
    torch.testing.assert_close(deriv, jvp, rtol=1e-10, atol=1e-12 * float(jvp.abs().mean()))
    # a wrong chain-rule factor (the unit-cube derivative) would be far outside these bounds
    light_cube = LightField(hidden=32, layers=3).double()
    light_cube.load_state_dict(light.state_dict())
    light_cube.bbox.copy_(CUBE.double())
    _, wrong = light_cube.with_derivative((x - box[0]) / (box[1] - box[0]) * 2 - 1, w)
    assert not torch.allclose(wrong, fd, rtol=1e-3, atol=1e-3 * float(fd.abs().mean()))


def test_directional_derivative_broadcasts_and_is_zero_where_clamped():
    """Broadcast inputs (points (N, 1, 3), directions (1, M, 3)) give the same derivative
    as expanded ones (bitwise the same arithmetic, so rtol 1e-12). Where ``y`` exceeds
    :data:`LOG_RADIANCE_MAX` the radiance is the constant ``scale e^30``; its directional
    derivative is then exactly 0 (and finite differences of the forward say the same)."""
    torch.manual_seed(11)
    light = LightField(hidden=16, layers=2).double()
    x = uniform_box_points(5, CUBE.double()).unsqueeze(1) * 0.9
    w = unit_vectors(7, torch.float64).unsqueeze(0)
    _, d_bc = light.with_derivative(x, w)
    _, d_ex = light.with_derivative(x.expand(5, 7, 3), w.expand(5, 7, 3))
    assert d_bc.shape == (5, 7, 3)
    torch.testing.assert_close(d_bc, d_ex, rtol=1e-12, atol=0)
    with torch.no_grad():
        light.net.out.bias.fill_(LOG_RADIANCE_MAX + 50.0)
    value, deriv = light.with_derivative(x.expand(5, 7, 3), w.expand(5, 7, 3))
    assert torch.isfinite(value).all()
    torch.testing.assert_close(value, torch.full_like(value, math.exp(LOG_RADIANCE_MAX)))
    assert (deriv == 0).all()


# ----------------------------------------------------------------------------------------
# 2. White furnace
# ----------------------------------------------------------------------------------------


class ConstantLight(LightField):
    """The furnace solution ``L = c`` everywhere, with zero derivative; keeps LightField's
    ``bbox`` and ``radiance_scale`` buffers (the losses read them)."""

    def __init__(self, c: torch.Tensor, bbox: torch.Tensor, scale: float):
        super().__init__(hidden=1, layers=1)
        self.bbox.copy_(bbox)
        self.radiance_scale.fill_(scale)
        self.register_buffer("c", c.clone())

    def forward(self, x, w):
        return self.c.expand(*torch.broadcast_shapes(x.shape, w.shape))

    def with_derivative(self, x, w):
        value = self.forward(x, w)
        return value, torch.zeros_like(value)


def furnace_medium(phase: str, sigma_a_scale: float, generator: torch.Generator):
    r = 6
    sigma_s = 0.1 + 20 * torch.rand(r, r, r, 3, generator=generator)
    sigma_a = sigma_a_scale * torch.rand(r, r, r, 3, generator=generator)
    g = (2 * torch.rand(r, r, r, generator=generator) - 1) * 0.9
    if phase == "hg":
        g = torch.full((r, r, r), 0.7)
    return GroundTruthMedium({"phase": phase, "chromatic": True}, sigma_a, sigma_s, g, SLAB)


@pytest.mark.parametrize("phase", ["isotropic", "hg", "varying_hg"])
def test_white_furnace_has_zero_residual_and_boundary_loss(phase):
    """sigma_a = 0 and a constant sky c: ``L = c`` solves the RTE exactly (no derivative,
    and ``sigma_t c = sigma_s S`` because every phase-sampled direction sees c). With
    c = (0.5, 2, 7) the sums of equal samples are exact in float32, so only rounding of
    ``sigma_t c`` against ``sigma_s S`` (terms <= 20 x 7 = 140, ulp ~1.5e-5, / scale 2.5)
    can remain: the bound 1e-5 is about one ulp. The boundary loss compares
    ``log1p(c / s)`` with itself: exactly 0, for the uniform and the sky-importance-sampled
    inflow directions alike.

    A known direct source k must add ``-sigma_s k / scale`` to both estimates, and the
    same field in an absorbing medium must give ``r = sigma_a c / scale`` at every point
    (so the zero above is not vacuous: the check fails when the balance is broken).
    """
    gen = torch.Generator().manual_seed(20)
    torch.manual_seed(21)
    c = torch.tensor([0.5, 2.0, 7.0])
    scale = 2.5
    light = ConstantLight(c, SLAB, scale)
    medium = furnace_medium(phase, 0.0, gen)
    dens = DensityPointSampler(medium.stacked[..., 3:6].sum(-1), SLAB)
    pts = collocation_points(1024, SLAB, dens, 0.5, gen)
    r_a, r_b = rte_residuals(light, medium, pts, n_dirs=8)
    assert r_a.shape == r_b.shape == (1024, 3)
    assert r_a.abs().max() < 1e-5 and r_b.abs().max() < 1e-5, (r_a.abs().max(), r_b.abs().max())
    assert abs(float(rte_loss(light, medium, pts, n_dirs=8))) < 1e-10
    # a known direct source k adds -sigma_s k / scale to both estimates (S = S_mc + S_direct)
    k = torch.tensor([0.25, 0.5, 1.0])
    r_a, r_b = rte_residuals(light, medium, pts, n_dirs=8,
                             direct_source=lambda x, w, props: k.expand_as(x))
    expected = -medium(pts).sigma_s * k / scale
    torch.testing.assert_close(r_a, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(r_b, expected, rtol=1e-5, atol=1e-5)

    env = EnvironmentMap(c.expand(16, 32, 3).clone())
    for sampler, fraction in ((None, 0.0), (EnvironmentDirectionSampler(env), 0.7)):
        bpts, bdirs = boundary_samples(777, SLAB, sampler, fraction, gen)
        inflow = env.lookup(-bdirs)
        torch.testing.assert_close(inflow, c.expand(777, 3))
        assert float(boundary_loss(light, bpts, bdirs, inflow)) == 0.0

    absorbing = furnace_medium(phase, 3.0, gen)
    r_a, r_b = rte_residuals(light, absorbing, pts, n_dirs=8)
    expected = absorbing(pts).sigma_a * c / scale
    assert expected.abs().min() > 1e-3
    torch.testing.assert_close(r_a, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(r_b, expected, rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------------------
# 3. Unbiased gradient of the squared residual
# ----------------------------------------------------------------------------------------


def sphere_quadrature(n_mu: int, n_phi: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss-Legendre in ``mu = w_z`` times the periodic trapezoid rule in ``phi``: nodes
    (n_mu n_phi, 3) and weights summing to 4 pi; spectrally accurate for smooth integrands."""
    mu, wmu = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = torch.tensor(mu), torch.tensor(wmu)
    phi = (torch.arange(n_phi, dtype=torch.float64) + 0.5) * 2 * math.pi / n_phi
    m, p = torch.meshgrid(mu, phi, indexing="ij")
    s = torch.sqrt(1 - m * m)
    nodes = torch.stack((s * torch.cos(p), s * torch.sin(p), m), -1).reshape(-1, 3)
    weights = (wmu[:, None] * (2 * math.pi / n_phi)).expand(n_mu, n_phi).reshape(-1)
    return nodes, weights


def exact_inscatter(light, x, w, g, quad) -> torch.Tensor:
    """``S(x, w) = int f(w . w') L(x, w') dw'`` by quadrature (differentiable in theta)."""
    nodes, weights = quad
    cos = w @ nodes.T  # (N, Q)
    f = torch.full_like(cos, 1 / (4 * math.pi)) if g is None else hg_reference(cos, g)
    radiance = light(x.unsqueeze(1), nodes.unsqueeze(0))  # (N, Q, 3)
    return ((weights * f).unsqueeze(-1) * radiance).sum(1)


@pytest.mark.parametrize("g", [None, 0.6])
def test_unbiased_square_gradient_matches_the_exact_residual_gradient(g, monkeypatch):
    """Gradient of ``unbiased_square(r_a, r_b)`` from :func:`rte_residuals` (2 directions
    per estimate), averaged over 4000 independent draws, equals the gradient of the mean
    squared *exact* residual; the naive ``mean(r_b^2)`` does not.

    Setup: float64 LightField (hidden 8, 1 layer, output weights x10 so that L varies by
    e^+-2 over directions), 12 fixed points and fixed travel directions (monkeypatched
    into rte_residuals), GroundTruthMedium with sigma_s = 4, sigma_a = 0.5, isotropic or
    HG(0.6). Draws are batched: each call replicates the 12 points 40 times, so its
    gradient is the mean of 40 i.i.d. draws; 100 calls give 100 i.i.d. batch means, whose
    sample standard deviation / sqrt(100) is the standard error ``se`` per parameter.

    Reference: the exact residual with ``(w . grad) L`` from ``torch.func.jvp`` and S from
    a Gauss-Legendre x trapezoid quadrature (64 x 128 nodes). Its own error is measured
    against 96 x 192 nodes and must be < 1e-9 relative, so it adds nothing to the bound.

    Bound: ``|mean - ref| <= 5 se + 1e-9 max|ref|`` per parameter. With ~80 parameters and
    a t(99) tail, a correct estimator fails with probability < 1e-3 (and the seeds are
    fixed). The naive estimator's bias is ``2 Cov(e, de)`` (the in-scattering noise ``e``
    with its own gradient), which does not average away: its max z-score must exceed 10,
    which shows that the test can see a biased gradient.
    """
    torch.manual_seed(30 if g is None else 31)
    light = LightField(hidden=8, layers=1, omega_0=30.0).double()
    with torch.no_grad():
        light.net.out.weight.mul_(10.0)
    r = 4
    medium = GroundTruthMedium({"phase": "isotropic" if g is None else "hg"},
                               torch.full((r, r, r, 3), 0.5), torch.full((r, r, r, 3), 4.0),
                               torch.full((r, r, r), 0.0 if g is None else g), CUBE)
    n, k, batches, n_dirs = 12, 40, 100, 2
    x = uniform_box_points(n, CUBE.double()) * 0.8
    w = unit_vectors(n, torch.float64)
    params = list(light.parameters())

    def flat_grad(loss, retain=False):
        return torch.cat([t.flatten() for t in torch.autograd.grad(loss, params,
                                                                   retain_graph=retain)])

    # the exact reference
    props = medium(x)
    fine, finer = sphere_quadrature(64, 128), sphere_quadrature(96, 192)
    s_exact = exact_inscatter(light, x, w, g, fine)
    with torch.no_grad():
        s_finer = exact_inscatter(light, x, w, g, finer)
    torch.testing.assert_close(s_exact.detach(), s_finer, rtol=1e-9, atol=0)
    radiance, deriv = torch.func.jvp(lambda p: light(p, w), (x,), (w,))
    r_exact = deriv + props.sigma_t * radiance - props.sigma_s * s_exact
    ref = flat_grad(r_exact.pow(2).mean())

    x_rep, w_rep = x.repeat(k, 1), w.repeat(k, 1)
    monkeypatch.setattr(rte_module, "sample_uniform_sphere", lambda xi: w_rep)
    ours, naive = [], []
    for _ in range(batches):
        r_a, r_b = rte_residuals(light, medium, x_rep, n_dirs)
        assert not r_a.requires_grad and r_b.requires_grad
        ours.append(flat_grad(unbiased_square(r_a, r_b), retain=True))
        naive.append(flat_grad(r_b.pow(2).mean()))
    ours_t, naive_t = torch.stack(ours), torch.stack(naive)
    se = ours_t.std(0) / math.sqrt(batches)
    z = (ours_t.mean(0) - ref) / (se + 1e-300)
    atol = 1e-9 * float(ref.abs().max())
    assert ((ours_t.mean(0) - ref).abs() <= 5 * se + atol).all(), (
        f"unbiased estimator off: max |z| = {z.abs().max():.2f}")
    naive_z = (naive_t.mean(0) - ref).abs() / (naive_t.std(0) / math.sqrt(batches))
    assert naive_z.max() > 10, f"the naive estimator's bias is invisible: {naive_z.max():.2f}"


@pytest.mark.parametrize("g0", [0.0, 0.005, 0.5, -0.7])
def test_inscatter_g_gradient_is_unbiased(g0):
    """The in-scattering estimate is differentiable in g through the sampled directions
    (reparameterisation); its g-gradient must be an unbiased estimate of
    ``d/dg int f_g(w . w') L(x, w') dw'``, including at g = 0 and in the series branch
    (|g| < 1e-2), where a wrong ``d cos / d g`` would bias it.

    Reference: autograd through the 64 x 128 quadrature of the HG formula
    (docs/conventions.md, "Phase function")
    (error < 1e-12, see the unbiasedness test above). Estimate: 40 independent calls with
    1000 directions per point, i.e. 40 i.i.d. batch means; ``|mean - ref| <= 5 se`` per
    point (8 points, t(39) tail: a correct estimator fails with probability ~1e-4). The
    bound has teeth: the g-gradient without the pathwise term (directions held fixed)
    would be 0, many standard errors away from the reference here.
    """
    torch.manual_seed(35)
    light = LightField(hidden=8, layers=1, omega_0=30.0).double()
    with torch.no_grad():
        light.net.out.weight.mul_(10.0)
    for p in light.parameters():
        p.requires_grad_(False)
    n = 8
    x = uniform_box_points(n, CUBE.double()) * 0.8
    w = unit_vectors(n, torch.float64)
    g_ref = torch.full((n,), g0, dtype=torch.float64, requires_grad=True)
    nodes, weights = sphere_quadrature(64, 128)
    cos = w @ nodes.T
    f = (1 - g_ref[:, None] ** 2) / (4 * math.pi * (1 + g_ref[:, None] ** 2
                                                    - 2 * g_ref[:, None] * cos) ** 1.5)
    s_exact = ((weights * f).unsqueeze(-1) * light(x.unsqueeze(1), nodes.unsqueeze(0))).sum(1)
    (ref,) = torch.autograd.grad(s_exact.sum(), g_ref)
    gen = torch.Generator().manual_seed(36)
    grads = []
    for _ in range(40):
        g = torch.full((n,), g0, dtype=torch.float64, requires_grad=True)
        s = inscattered_radiance(light, x, w, g, 1000, generator=gen)
        grads.append(torch.autograd.grad(s.sum(), g)[0])
    grads_t = torch.stack(grads)
    se = grads_t.std(0) / math.sqrt(len(grads))
    err = (grads_t.mean(0) - ref).abs()
    assert (err <= 5 * se).all(), (err / se).max()
    assert (ref.abs() / se).max() > 10  # a zero gradient would fail


def test_detached_inscatter_keeps_only_the_g_gradient():
    """``detach=True`` (the neural-radiosity habit) returns the same values for the same
    random numbers, no gradient into the light field, and the same gradient to g (the
    directions still move with g); with an isotropic phase it carries no graph at all."""
    torch.manual_seed(37)
    light = LightField(hidden=8, layers=1)
    x = uniform_box_points(16, CUBE)
    w = unit_vectors(16)
    params = list(light.parameters())
    g = torch.full((16,), 0.4, requires_grad=True)
    full = inscattered_radiance(light, x, w, g, 8, generator=torch.Generator().manual_seed(1))
    det = inscattered_radiance(light, x, w, g, 8, detach=True,
                               generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(det, full, rtol=0, atol=0)
    grads_full = torch.autograd.grad(full.sum(), [g, *params])
    grads_det = torch.autograd.grad(det.sum(), [g, *params], allow_unused=True)
    torch.testing.assert_close(grads_det[0], grads_full[0])
    assert all(gr is None or (gr == 0).all() for gr in grads_det[1:])
    assert any((gr != 0).any() for gr in grads_full[1:])
    iso = inscattered_radiance(light, x, w, None, 8, detach=True)
    assert not iso.requires_grad


# ----------------------------------------------------------------------------------------
# 4. Henyey-Greenstein sampling
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("g", [-0.9, 0.0, 1e-4, 0.5, 0.9])
def test_hg_cosines_follow_the_hg_density(g):
    """200k cosines from ``sample_hg_cos`` in 40 equal bins over [-1, 1] against bin
    probabilities ``2 pi int f(cos) dcos`` of ``hg_phase``, integrated with 4000-point
    midpoint rules per bin (relative error < 1e-5 even at g = 0.9, whose peak has width
    ~(1 - g)^2 / g ~ 0.01 >> the 1.25e-5 step); the integrated probabilities must sum to
    1 within 1e-5 (normalisation of hg_phase) and match the HG formula (docs/conventions.md,
    "Phase function"). Pearson's statistic must stay below the 0.999 quantile of
    chi-square(39): a correct sampler fails with probability 1e-3, a wrong lobe sign or a
    missing (1 - g^2) by thousands.
    The sample mean cosine must be g (HG's defining moment) within 5 standard errors.
    ``sample_hg`` turns the same cosines into directions: for random unit travel directions
    w its outputs are unit vectors whose cosine with w is ``sample_hg_cos``'s (float64
    rounding, 1e-12), so the histogram covers the directions too."""
    torch.manual_seed(40)
    n, bins, sub = 200_000, 40, 4000
    xi = torch.rand(n, dtype=torch.float64)
    cos = sample_hg_cos(torch.tensor(g, dtype=torch.float64), xi)
    assert torch.isfinite(cos).all() and cos.abs().max() <= 1.0
    counts = torch.histc(cos, bins=bins, min=-1.0, max=1.0)
    edges = torch.linspace(-1.0, 1.0, bins + 1, dtype=torch.float64)
    width = edges[1] - edges[0]
    mids = edges[:-1, None] + (torch.arange(sub, dtype=torch.float64) + 0.5) / sub * width
    probs = 2 * math.pi * hg_phase(mids, g).mean(-1) * width
    torch.testing.assert_close(probs, 2 * math.pi * hg_reference(mids, g).mean(-1) * width,
                               rtol=1e-12, atol=0)
    assert abs(float(probs.sum()) - 1.0) < 1e-5
    expected = probs * n
    assert expected.min() > 5  # Pearson's approximation holds
    stat = float(((counts - expected) ** 2 / expected).sum())
    assert stat < chi2.ppf(0.999, bins - 1), f"g={g}: chi2 = {stat:.1f}"
    mean_se = float(cos.std()) / math.sqrt(n)
    assert abs(float(cos.mean()) - g) < 5 * mean_se
    w = torch.randn(n, 3, dtype=torch.float64)
    w = w / w.norm(dim=-1, keepdim=True)
    out = sample_hg(w, torch.full((n,), g, dtype=torch.float64),
                    torch.stack((xi, torch.rand(n, dtype=torch.float64)), -1))
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(n, dtype=torch.float64))
    torch.testing.assert_close((out * w).sum(-1), cos, rtol=0, atol=1e-12)


def test_hg_sampling_and_phase_have_finite_correct_gradients_at_zero_g():
    """g = 0 exactly (the branch the Taylor series guards): values and gradients finite.
    Closed forms: d cos / d g at g = 0 is 3/2 (1 - a^2), a = 2 xi - 1 (first-order term of
    the inversion), and d f / d g at g = 0 is 3 cos / (4 pi). Both are float64 rounding
    comparisons (rtol 1e-12). Directions from ``sample_hg``/``sample_phase`` and their
    gradients stay finite and unit length, including for travel directions on the poles
    (the orthonormal-basis singularity at w_z = -1). Gradients of ``sample_hg`` and
    ``hg_phase`` stay finite near 0, at the series switch and at +-G_MAX too."""
    torch.manual_seed(41)
    xi = torch.rand(5000, dtype=torch.float64)
    g = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    cos = sample_hg_cos(g, xi)
    (grad,) = torch.autograd.grad(cos.sum(), g)
    a = 2 * xi - 1
    assert torch.isfinite(cos).all() and torch.isfinite(grad)
    torch.testing.assert_close(cos.detach(), a, rtol=0, atol=1e-15)
    torch.testing.assert_close(grad, (1.5 * (1 - a * a)).sum(), rtol=1e-12, atol=0)
    per_sample = torch.autograd.functional.jacobian(
        lambda gg: sample_hg_cos(gg.expand(64), xi[:64]), torch.zeros(1, dtype=torch.float64))
    torch.testing.assert_close(per_sample.squeeze(-1), 1.5 * (1 - a[:64] ** 2), rtol=1e-12,
                               atol=0)

    cos_grid = torch.linspace(-1, 1, 101, dtype=torch.float64)
    f = hg_phase(cos_grid, g)
    df = torch.autograd.functional.jacobian(lambda gg: hg_phase(cos_grid, gg),
                                            torch.tensor(0.0, dtype=torch.float64))
    assert torch.isfinite(f).all() and torch.isfinite(df).all()
    torch.testing.assert_close(f.detach(), torch.full_like(cos_grid, 1 / (4 * math.pi)))
    torch.testing.assert_close(df, 3 * cos_grid / (4 * math.pi), rtol=1e-12, atol=1e-15)

    poles = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]],
                         dtype=torch.float64)
    w = poles.repeat(250, 1)
    xi2 = torch.rand(1000, 2, dtype=torch.float64)
    g_vec = torch.zeros(1000, dtype=torch.float64, requires_grad=True)
    for out in (sample_hg(w, g_vec, xi2), sample_phase(w, g_vec, xi2)):
        (gr,) = torch.autograd.grad(out.sum(), g_vec)
        assert torch.isfinite(out).all() and torch.isfinite(gr).all()
        torch.testing.assert_close(out.norm(dim=-1), torch.ones(1000, dtype=torch.float64))
        # at g = 0 the cosine with w is the uniform a = 2 xi - 1
        torch.testing.assert_close((out * w).sum(-1).detach(), 2 * xi2[:, 0] - 1,
                                   rtol=0, atol=1e-12)
    for g0 in (1e-4, -1e-4, 1e-2, -1e-2, 0.3, -0.95, 0.95):
        g_vec = torch.full((1000,), g0, dtype=torch.float64, requires_grad=True)
        (gr,) = torch.autograd.grad(sample_hg(w, g_vec, xi2).sum(), g_vec)
        gp = torch.tensor(g0, dtype=torch.float64, requires_grad=True)
        (gphase,) = torch.autograd.grad(hg_phase(cos_grid, gp).sum(), gp)
        assert torch.isfinite(gr).all() and torch.isfinite(gphase), g0


def test_hg_sampler_is_continuous_across_its_series_branch():
    """The series branch (|g| < 1e-2) and the closed form must map xi to the same cosine
    where they meet: the third-order term of the inversion in g is
    ``g^3 (-5/2 a^4 + 3 a^2 - 1/2)`` (sympy), at most 5e-7 at |g| = 1e-2, so the jump must
    be below 1e-6. The reparameterisation gradient must also be continuous: it is checked
    against central differences of the sampler (float64, h = 1e-7 inside each branch;
    truncation ~h^2 and rounding ~1e-16/h ~ 1e-9, bound 1e-6)."""
    xi = (torch.arange(999, dtype=torch.float64) + 0.5) / 999
    for edge in (1e-2, -1e-2):
        below = sample_hg_cos(torch.tensor(edge * (1 - 1e-12), dtype=torch.float64), xi)
        above = sample_hg_cos(torch.tensor(edge * (1 + 1e-12), dtype=torch.float64), xi)
        assert (below - above).abs().max() < 1e-6
        below32 = sample_hg_cos(torch.tensor(edge * (1 - 1e-6)), xi.float())
        above32 = sample_hg_cos(torch.tensor(edge * (1 + 1e-6)), xi.float())
        # float32: the closed form divides roundings of ~6e-8 by 2 g = 0.02 (~3e-6 each)
        assert (below32 - above32).abs().max() < 3e-5
    for g0 in (-0.5, -0.011, -0.009, 0.0, 0.005, 0.009, 0.011, 0.3, 0.9):
        g = torch.full_like(xi, g0, requires_grad=True)
        (grad,) = torch.autograd.grad(sample_hg_cos(g, xi).sum(), g)
        h = 1e-7
        fd = (sample_hg_cos(g.detach() + h, xi) - sample_hg_cos(g.detach() - h, xi)) / (2 * h)
        inside = (xi > 1e-3) & (xi < 1 - 1e-3)  # away from the clamp at cos = +-1
        torch.testing.assert_close(grad[inside], fd[inside], rtol=1e-6, atol=1e-6)


# ----------------------------------------------------------------------------------------
# 5. Medium heads follow the scene's effects
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("chromatic", [True, False])
@pytest.mark.parametrize("modulation", ["siren", "grid"])
def test_medium_heads_follow_the_effects(chromatic, modulation):
    """isotropic: g is None and nothing g-shaped exists (no g parameter, modulation width
    K); hg: exactly one scalar g parameter, g identical at every point and equal to
    ``G_MAX tanh(g_shared)``, width K; varying_hg: a g output channel (width K + 1),
    g varies over points and stays within G_MAX. K = 6 (a, s per RGB channel) for
    chromatic scenes; grey ones have K = 4: one sigma_t channel (..., 1), the same in R, G
    and B, and an RGB albedo that varies per channel (the model of the scene spec, of
    Mitsuba's one-channel sigma_t grid and of stage=dpt)."""
    torch.manual_seed(50)
    c = 3 if chromatic else 1
    k = 6 if chromatic else 4
    pts = uniform_box_points(300, SLAB)
    for phase, width in (("isotropic", k), ("hg", k), ("varying_hg", k + 1)):
        network = (partial(Siren, hidden=16, layers=2) if modulation == "siren"
                   else partial(GridModulation, resolution=5))
        medium = NeuralMedium({"phase": phase, "chromatic": chromatic}, modulation=network)
        medium.bbox.copy_(SLAB)
        if modulation == "grid":
            with torch.no_grad():
                medium.modulation.values.normal_()
        props = medium(pts)
        assert props.sigma_a.shape == props.sigma_s.shape == props.albedo.shape == (300, 3)
        assert props.sigma_t.shape == (300, c)
        assert (props.sigma_a > 0).all() and (props.sigma_s > 0).all()
        torch.testing.assert_close(props.albedo, props.sigma_s / props.sigma_t)
        torch.testing.assert_close(props.sigma_a + props.sigma_s,
                                   props.sigma_t.expand(300, 3))
        if modulation == "grid":  # random values: the albedo differs between channels
            assert (props.albedo[:, 0] - props.albedo[:, 2]).abs().max() > 0.1
        out_width = (medium.modulation.out.out_features if modulation == "siren"
                     else medium.modulation.values.shape[-1])
        assert out_width == width
        g_params = [name for name, _ in medium.named_parameters()
                    if name.split(".")[-1].startswith("g")]
        if phase == "isotropic":
            assert props.g is None and medium.g_shared is None and not g_params
        elif phase == "hg":
            assert g_params == ["g_shared"] and medium.g_shared.numel() == 1
            with torch.no_grad():
                medium.g_shared.fill_(0.3)
            g = medium(pts).g
            assert g.shape == (300,)
            torch.testing.assert_close(g, torch.full_like(g, G_MAX * math.tanh(0.3)))
        else:
            assert medium.g_shared is None and not g_params
            assert props.g.shape == (300,) and props.g.std() > 1e-3
            assert props.g.abs().max() <= G_MAX


def test_grey_media_have_one_extinction_channel_and_an_rgb_albedo():
    """Grey extinction (``chromatic=false``) is one sigma_t channel with an RGB albedo.

    GroundTruthMedium of a grey spec's grids holds, at the cell centres (where trilinear
    lookups return the cells exactly), the very values Mitsuba renders
    (:func:`mitsuba_properties`: sigma_t of channel 0, albedo sigma_s / sigma_t per channel),
    so forward mode sees the coloured albedo, not red's for all three channels. A fresh
    grey NeuralMedium starts at sigma_t = rho (the EA density) and albedo ``init_albedo``
    in every channel, as the chromatic one does."""
    from nrt.mitsuba.scene import mitsuba_properties
    from nrt.physics.volume import cell_centres

    gen = torch.Generator().manual_seed(51)
    r = 4
    sigma_t = 0.2 + 3 * torch.rand(r, r, r, 1, generator=gen)
    albedo = torch.rand(r, r, r, 3, generator=gen)
    albedo[0, 0, 0] = torch.tensor([0.9, 0.5, 0.1])
    sigma_t[1, 2, 3] = 0.0  # an empty cell: albedo 0 there, as Mitsuba's grid has it
    grids = {"sigma_a": sigma_t * (1 - albedo), "sigma_s": sigma_t * albedo,
             "g": torch.zeros(r, r, r)}
    effects = {"phase": "isotropic", "chromatic": False}
    medium = GroundTruthMedium(effects, grids["sigma_a"], grids["sigma_s"], grids["g"], SLAB)
    props = medium(cell_centres(r, SLAB).double())
    ref = mitsuba_properties({k: v.numpy() for k, v in grids.items()}, effects)
    assert props.sigma_t.shape == (r, r, r, 1) and props.albedo.shape == (r, r, r, 3)
    torch.testing.assert_close(props.sigma_t, torch.as_tensor(ref["sigma_t"]).double())
    torch.testing.assert_close(props.albedo, torch.as_tensor(ref["albedo"]).double())
    assert props.albedo[0, 0, 0].tolist() == pytest.approx([0.9, 0.5, 0.1], abs=1e-6)
    torch.testing.assert_close(props.sigma_s, grids["sigma_s"].double(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(props.sigma_a, grids["sigma_a"].double(), rtol=1e-5, atol=1e-6)

    fresh = NeuralMedium({"phase": "hg", "chromatic": False},
                         modulation=partial(GridModulation, resolution=3), init_albedo=0.7)
    start = fresh(uniform_box_points(50, CUBE))
    torch.testing.assert_close(start.sigma_t, torch.ones(50, 1))
    torch.testing.assert_close(start.albedo, torch.full((50, 3), 0.7))


@pytest.mark.parametrize("fill", [1e6, -1e6, 1e30])
def test_medium_exponents_are_clamped(fill):
    """Huge modulation outputs: sigma saturates at ``exp(EXPONENT_RANGE)`` (finite, > 0),
    g at +-G_MAX, albedo and gradients stay finite."""
    medium = NeuralMedium({"phase": "varying_hg", "chromatic": True},
                          modulation=partial(GridModulation, resolution=4))
    with torch.no_grad():
        medium.modulation.values.fill_(fill)
    props = medium(uniform_box_points(64, CUBE))
    for t in (props.sigma_a, props.sigma_s, props.albedo, props.g):
        assert torch.isfinite(t).all()
    bound = EXPONENT_RANGE[1] if fill > 0 else EXPONENT_RANGE[0]
    torch.testing.assert_close(props.sigma_a, torch.full_like(props.sigma_a, math.exp(bound)))
    torch.testing.assert_close(props.sigma_s, torch.full_like(props.sigma_s, math.exp(bound)))
    assert (props.sigma_s > 0).all()
    torch.testing.assert_close(props.g.abs(), torch.full_like(props.g, G_MAX))
    loss = props.sigma_t.sum() + props.g.sum() + props.albedo.sum()
    loss.backward()
    assert torch.isfinite(medium.modulation.values.grad).all()


# ----------------------------------------------------------------------------------------
# 6. Splitting the sun off the environment
# ----------------------------------------------------------------------------------------


def texel_dirs(h: int, w: int) -> torch.Tensor:
    """The texel placement of docs/conventions.md ("Environment maps"): row j at
    t = pi j / (H - 1), column i at u = (i+.5)/W,
    d = (sin t sin 2 pi u, cos t, -sin t cos 2 pi u)."""
    t = math.pi * torch.arange(h, dtype=torch.float64) / (h - 1)
    u = (torch.arange(w, dtype=torch.float64) + 0.5) / w
    t, u = torch.meshgrid(t, u, indexing="ij")
    return torch.stack((torch.sin(t) * torch.sin(2 * math.pi * u), torch.cos(t),
                        -torch.sin(t) * torch.cos(2 * math.pi * u)), -1)


def lum(rgb: torch.Tensor) -> torch.Tensor:
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def test_split_sun_conserves_radiance_and_sun_power():
    """Sky 0.5 plus a coloured 3x2-texel sun (and a dimmer second sun far from it):

    - E_rest's luminance <= threshold (float32 rounding: rtol 1e-6), bright texels keep
      their colour (scaled by threshold / luminance), all others are unchanged;
    - E_rest + the excess (computed here) == the original texelwise;
    - each sun direction is within one texel (pi / (H - 1)) of the power-weighted mean of
      its texels' directions (docs/conventions.md, "Environment maps", written out here);
    - each irradiance equals sum(excess x sin(t_j) (pi / (H - 1)) (2 pi / W)) (rtol 1e-5:
      float32 output of a float64 sum);
    - with max_suns = 1 the dimmer sun stays in E_rest unchanged; a map without anything
      above the threshold gives zero suns and E_rest == E.
    """
    h, w, threshold = 33, 64, 4.0
    sky = torch.full((h, w, 3), 0.5)
    sun_rgb = torch.tensor([900.0, 1000.0, 600.0])
    sky[9:12, 20:22] = sun_rgb
    sky[12, 19] = sun_rgb * torch.tensor([1.0, 1.1, 1.2])  # same cluster (within 20 deg)
    sky[16, 52:54] = torch.tensor([60.0, 50.0, 40.0])  # a second, dimmer sun
    env = EnvironmentMap(sky.clone())
    rest, dirs, irr = split_sun(env, threshold)
    assert dirs.shape == (2, 3) and irr.shape == (2, 3)

    lum0 = lum(sky.double())
    bright = lum0 > threshold
    factor = torch.where(bright, threshold / lum0, torch.ones_like(lum0))
    excess = sky.double() * (1 - factor).unsqueeze(-1)
    rest_r = rest.radiance.double()
    assert float(lum(rest_r).max()) <= threshold * (1 + 1e-6)
    torch.testing.assert_close(rest_r, sky.double() * factor.unsqueeze(-1), rtol=1e-6, atol=0)
    torch.testing.assert_close(rest_r + excess, sky.double(), rtol=1e-6, atol=0)

    td = texel_dirs(h, w)
    solid = (torch.sin(math.pi * torch.arange(h, dtype=torch.float64) / (h - 1))
             * (math.pi / (h - 1)) * (2 * math.pi / w))[:, None].expand(h, w)
    clusters = torch.zeros(h, w, dtype=torch.bool), torch.zeros(h, w, dtype=torch.bool)
    clusters[0][9:13, 19:22] = True
    clusters[1][16, 52:54] = True
    for k, member in enumerate(clusters):
        member = member & bright
        power = excess[member] * solid[member].unsqueeze(-1)
        torch.testing.assert_close(irr[k].double(), power.sum(0), rtol=1e-5, atol=0)
        mean_dir = (td[member] * lum(power).unsqueeze(-1)).sum(0)
        mean_dir = mean_dir / mean_dir.norm()
        angle = math.acos(min(1.0, float(dirs[k].double() @ mean_dir)))
        assert angle <= math.pi / (h - 1), (k, math.degrees(angle))
        torch.testing.assert_close(dirs[k].norm(), torch.tensor(1.0))

    rest1, dirs1, irr1 = split_sun(env, threshold, max_suns=1)
    assert dirs1.shape == (1, 3)
    torch.testing.assert_close(irr1[0], irr[0])
    torch.testing.assert_close(rest1.radiance[16, 52:54], sky[16, 52:54])
    torch.testing.assert_close(rest1.radiance[9:12, 20:22], rest.radiance[9:12, 20:22])

    calm = EnvironmentMap(torch.full((h, w, 3), 0.5))
    rest0, dirs0, irr0 = split_sun(calm, threshold)
    assert dirs0.shape == (0, 3) and irr0.shape == (0, 3)
    torch.testing.assert_close(rest0.radiance, calm.radiance, rtol=0, atol=0)


# ----------------------------------------------------------------------------------------
# 7. First scattering of known lights
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("g", [None, 0.7, -0.4])
def test_direct_inscatter_closed_forms(g):
    """Homogeneous chromatic GroundTruthMedium in SLAB (sigma_t = (0.6, 1.3, 2.2)): the
    midpoint rule integrates a constant exactly, so

    - sun: ``f(-l . w) E exp(-sigma_t t_exit)``, t_exit the distance to the box boundary
      toward the sun (computed axis by axis here);
    - point light inside the box: ``f I exp(-sigma_t d) / d^2``;
    - point light outside the box: ``f I exp(-sigma_t t_exit) / d^2`` (only the part of
      the segment inside the box attenuates).

    f is the HG formula of docs/conventions.md in directions of travel (light travels along -l, so
    cos = -l . w; g > 0 favours w ~ -l). Only float32 rounding differs: rtol 1e-5.
    """
    torch.manual_seed(70)
    n = 64
    sig = torch.tensor([0.6, 1.3, 2.2])
    r = 3
    medium = GroundTruthMedium({"phase": "hg"}, (0.25 * sig).expand(r, r, r, 3),
                               (0.75 * sig).expand(r, r, r, 3), torch.zeros(r, r, r), SLAB)
    sigma_t = lambda p: medium(p).sigma_t  # noqa: E731
    x = SLAB[0] + (0.05 + 0.9 * torch.rand(n, 3)) * (SLAB[1] - SLAB[0])
    w = unit_vectors(n)
    g_t = None if g is None else torch.full((n,), g)

    def phase(cos):
        return torch.full_like(cos, 1 / (4 * math.pi)) if g is None else hg_reference(cos, g)

    sun = torch.tensor([0.3, 0.8, -0.5])
    sun = sun / sun.norm()
    e_sun = torch.tensor([2.0, 3.0, 5.0])
    lights = DirectLights(torch.zeros(0, 3), torch.zeros(0, 3), sun[None], e_sun[None])
    out = direct_inscatter(x, w, g_t, lights, sigma_t, SLAB, n_steps=4)
    t_exit = box_exit_distance(x, sun.expand(n, 3), SLAB)
    expected = (phase(-(w @ sun)).unsqueeze(-1) * e_sun
                * torch.exp(-sig * t_exit.unsqueeze(-1)))
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=0)

    intensity = torch.tensor([5.0, 4.0, 3.0])
    for p in (torch.tensor([0.2, 0.1, 0.4]), torch.tensor([4.0, 2.5, -3.0])):
        inside = bool(((p > SLAB[0]) & (p < SLAB[1])).all())
        point = DirectLights(p[None], intensity[None], torch.zeros(0, 3), torch.zeros(0, 3))
        out = direct_inscatter(x, w, g_t, point, sigma_t, SLAB, n_steps=4)
        d = (p - x).norm(dim=-1)
        toward = (p - x) / d.unsqueeze(-1)
        length = d if inside else box_exit_distance(x, toward, SLAB)
        assert (length <= d + 1e-6).all()
        expected = (phase(-(toward * w).sum(-1)) / d**2).unsqueeze(-1) * intensity \
            * torch.exp(-sig * length.unsqueeze(-1))
        torch.testing.assert_close(out, expected, rtol=1e-5, atol=0)


def test_direct_inscatter_transmittance_follows_the_midpoint_rule():
    """Along the sun ray ``x + t l`` a linear extinction ``a + b y`` is integrated exactly
    by the midpoint rule (closed form ``a t + b (x_y t + l_y t^2 / 2)``); a quadratic
    ``a + b y^2`` is off by exactly ``-T^3 (2 b l_y^2) / (24 n^2)`` (composite midpoint
    error for a constant second derivative), which is checked to 1e-5 relative, so the
    samples must sit at the segment's midpoints, from 0 to the exit distance T."""
    torch.manual_seed(71)
    n = 32
    x = SLAB[0] + (0.1 + 0.8 * torch.rand(n, 3, dtype=torch.float64)) * (SLAB[1] - SLAB[0])
    w = unit_vectors(n, torch.float64)
    sun = torch.tensor([0.3, 0.8, -0.5], dtype=torch.float64)
    sun = sun / sun.norm()
    lights = DirectLights(torch.zeros(0, 3), torch.zeros(0, 3), sun[None].float(),
                          torch.ones(1, 3))
    box = SLAB.double()
    t_exit = box_exit_distance(x, sun.expand(n, 3), box)
    # use the sun direction exactly as the library sees it (float32-rounded)
    ly = float(lights.sun_directions[0, 1])
    a, b, steps = 0.4, 0.9, 6
    f_iso = 1 / (4 * math.pi)
    linear = direct_inscatter(x, w, None, lights, lambda p: (a + b * p[..., 1:2]), box, steps)
    tau_lin = a * t_exit + b * (x[:, 1] * t_exit + ly * t_exit**2 / 2)
    torch.testing.assert_close(linear[:, 0], f_iso * torch.exp(-tau_lin), rtol=1e-5, atol=0)
    quad = direct_inscatter(x, w, None, lights, lambda p: (a + b * p[..., 1:2] ** 2), box, steps)
    y0 = x[:, 1]
    tau_exact = a * t_exit + b * (y0**2 * t_exit + y0 * ly * t_exit**2 + ly**2 * t_exit**3 / 3)
    tau_mid = tau_exact - t_exit**3 * 2 * b * ly**2 / (24 * steps**2)
    torch.testing.assert_close(quad[:, 0], f_iso * torch.exp(-tau_mid), rtol=1e-5, atol=0)


# ----------------------------------------------------------------------------------------
# 8. Boundary samples
# ----------------------------------------------------------------------------------------


def test_boundary_samples_lie_on_faces_flow_in_and_follow_face_areas():
    """Non-cubic box SLAB (face areas 4, 12, 3 for the x, y, z pairs):

    - every point lies exactly on one face (its coordinate equals the bound), inside the
      face's rectangle;
    - every direction is a unit vector with ``w . n < 0`` for that face's outward normal,
      also with sky-importance sampling (a bright sun below the horizon, so many of its
      directions do not flow in through a given face and must be replaced);
    - the stratified per-face counts equal ``n area / total`` within 1 (rounding);
    - uniform inflow: ``|w . n|`` is uniform on [0, 1] for a uniform hemisphere, checked
      by a Kolmogorov-Smirnov test at p > 1e-3;
    - points are uniform on each face: the per-face mean of each free coordinate is the
      face centre within 5 standard errors (extent / sqrt(12 m)).
    """
    gen = torch.Generator().manual_seed(80)
    n = 6000
    sky = torch.full((16, 32, 3), 0.2)
    sky[12, 5] = 5000.0
    sampler = EnvironmentDirectionSampler(EnvironmentMap(sky))
    ext = SLAB[1] - SLAB[0]
    areas = torch.stack([ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]]).repeat_interleave(2)
    for env, fraction in ((None, 0.0), (sampler, 0.6)):
        pts, w = boundary_samples(n, SLAB, env, fraction, gen)
        assert pts.shape == w.shape == (n, 3)
        on_lo, on_hi = pts == SLAB[0], pts == SLAB[1]
        on = on_lo | on_hi
        assert (on.sum(-1) == 1).all()
        assert ((pts >= SLAB[0]) & (pts <= SLAB[1])).all()
        normal = on_hi.float() - on_lo.float()
        assert ((w * normal).sum(-1) < 0).all()
        torch.testing.assert_close(w.norm(dim=-1), torch.ones(n), rtol=0, atol=1e-5)
        face = on.float().argmax(-1) * 2 + on_hi.any(-1).long()
        counts = torch.bincount(face, minlength=6).double()
        assert (counts - n * areas / areas.sum()).abs().max() <= 1.0, counts
        for f in range(6):
            sel = face == f
            m = int(sel.sum())
            for ax in range(3):
                if ax == f // 2:
                    continue
                centre = float(SLAB[:, ax].mean())
                se = float(ext[ax]) / math.sqrt(12 * m)
                assert abs(float(pts[sel, ax].mean()) - centre) < 5 * se
        if env is None:
            assert kstest((-(w * normal).sum(-1)).numpy(), "uniform").pvalue > 1e-3
        else:
            # the sun's inflowing direction (light travels along -d) is over-represented
            d_sun = -texel_dirs(16, 32)[12, 5].float()
            near = (w @ d_sun > math.cos(math.radians(15))).float().mean()
            assert near > 0.2


def test_density_point_sampler_follows_the_grid():
    """``DensityPointSampler`` reads its grid ``[z, y, x]``: a density in one cell puts
    every point inside that cell's world bounds; two cells weighted 1 : 3 split the points
    1 : 3 within 5 binomial standard errors; ``collocation_points`` mixes in the asked
    fraction (the rest uniform over the whole box)."""
    gen = torch.Generator().manual_seed(90)
    r = 4
    cell = SLAB.double()
    size = (cell[1] - cell[0]) / r
    dens = torch.zeros(r, r, r)
    dens[3, 1, 0] = 1.0  # z = 3, y = 1, x = 0
    pts = DensityPointSampler(dens, SLAB).sample(2000, gen).double()
    lo = cell[0] + torch.tensor([0, 1, 3], dtype=torch.float64) * size
    assert ((pts >= lo - 1e-6) & (pts <= lo + size + 1e-6)).all()
    dens = torch.zeros(r, r, r)
    dens[0, 0, 0], dens[2, 3, 1] = 1.0, 3.0
    n = 8000
    pts = DensityPointSampler(dens, SLAB).sample(n, gen).double()
    idx = ((pts - cell[0]) / size).floor().long().clamp(0, r - 1)
    second = (idx == torch.tensor([1, 3, 2])).all(-1)
    assert (second | (idx == 0).all(-1)).all()
    se = math.sqrt(n * 0.75 * 0.25)
    assert abs(int(second.sum()) - 0.75 * n) < 5 * se
    mixed = collocation_points(n, SLAB, DensityPointSampler(dens, SLAB), 0.25, gen).double()
    idx = ((mixed - cell[0]) / size).floor().long().clamp(0, r - 1)
    in_cells = (idx == torch.tensor([1, 3, 2])).all(-1) | (idx == 0).all(-1)
    # 25% from the density plus 75% uniform, of which 2 / 64 land in the two cells
    p = 0.25 + 0.75 * 2 / r**3
    assert abs(float(in_cells.float().mean()) - p) < 5 * math.sqrt(p * (1 - p) / n)
