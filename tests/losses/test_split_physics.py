"""Physics of split stage 2 against closed forms, quadrature and Mitsuba: spherical
harmonics and HG, the environment sampler's density, the sky's first scattering (MIS),
the SH projection of uncollided light, the transport target, a white furnace solved by
the transport objective alone, the voxel medium, and the first-scattering image against
Mitsuba at order 1.

Monte Carlo estimates are compared with z-scores: the estimate's standard error comes from
its own independent repetitions, and |z| < 5 fails by chance with probability < 1e-6."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nrt.cameras import Intrinsics, look_at
from nrt.errors import NrtError
from nrt.losses.adjoint import adjoint_target, medium_sensitivity
from nrt.losses.transport import scattered_target, transport_loss, unrolled_inscatter
from nrt.mitsuba.scene import scene_dict
from nrt.mitsuba.variant import select_variant
from nrt.modules.fields.coarse_to_fine import (
    check_schedule,
    decaying_lr,
    ramp_in,
    resample_parameter,
    resolution_at,
)
from nrt.modules.fields.medium import GroundTruthMedium, MediumProperties, NeuralMedium
from nrt.modules.fields.sh_light_field import SHGrid, SHGridLightField
from nrt.modules.fields.voxel_medium import VoxelMedium
from nrt.modules.renderers.volume import render_view_rays
from nrt.physics.direct_light import DirectLights
from nrt.physics.envmap import EnvironmentDirectionSampler, EnvironmentMap
from nrt.physics.phase import hg_phase, isotropic_phase, sample_uniform_sphere
from nrt.physics.sh import num_coefficients, phase_band_factors, sh_basis
from nrt.physics.sky_light import sky_inscatter, uncollided_sh, uncollided_sh_skies
from nrt.physics.volume import cell_centres, ray_box_intersect
from tests.mc_stats import compare, footprint_average
from tests.mitsuba.test_mitsuba_physics import SEEDS, check, make_spec, render_pair, smooth_sky

pytestmark = pytest.mark.unit

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


def bright_spot_sky(height: int = 16, width: int = 32) -> EnvironmentMap:
    """The smooth test sky plus a 200x brighter texel (a sun-like spot left in the sky)."""
    sky = torch.from_numpy(smooth_sky(height, width)).double()
    sky[5, 9] *= 200.0
    return EnvironmentMap(sky)


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


def homogeneous(sigma_a, sigma_s, g: float | None, n: int = 4) -> GroundTruthMedium:
    """A homogeneous chromatic medium filling :data:`BOX` (float64)."""
    phase = "isotropic" if g is None else "hg"
    shape = (n, n, n, 3)
    return GroundTruthMedium({"phase": phase, "chromatic": True},
                             torch.tensor(sigma_a).expand(shape),
                             torch.tensor(sigma_s).expand(shape),
                             torch.full((n, n, n), 0.0 if g is None else g), BOX).double()


def sky_reference(x, w, g, sigma_t, env) -> torch.Tensor:
    """``S_u`` by quadrature over look directions d: ``int f(-d . w) T(x, d) E(d) dd``
    with the exact transmittance of a homogeneous box, ``exp(-sigma_t t_exit)``."""
    _, t_exit, _ = ray_box_intersect(x.expand_as(QUAD), QUAD, BOX)
    cos = -(QUAD @ w)
    f = isotropic_phase(cos) if g is None else hg_phase(cos, g)
    rad = torch.exp(-sigma_t * t_exit[:, None]) * env.lookup(QUAD)
    return (f[:, None] * rad).mean(0) * 4 * math.pi


@pytest.mark.parametrize("g", [None, 0.6, -0.4])
def test_sky_first_scattering_matches_quadrature(g):
    """MIS estimate of the sky's first scattering at three points (centre, off-centre,
    near a face) in a homogeneous chromatic box, against quadrature with the exact
    transmittance: |z| < 5 per channel, the standard error from 400 independent estimates.
    The shadow rays' jittered strata estimate the optical depth of a homogeneous medium
    exactly, so any deviation is a wrong density or weight. The derivative with respect to
    sigma_t (through T) matches the quadrature's derivative the same way."""
    torch.manual_seed(0)
    env = bright_spot_sky()
    sampler = EnvironmentDirectionSampler(env)
    sigma_t = torch.tensor([0.4, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.5, 0.2], [0.9, 0.1, -0.6]],
                       dtype=torch.float64)
    w = torch.nn.functional.normalize(torch.tensor([0.2, 0.7, -0.4], dtype=torch.float64), dim=0)
    reps = 400
    x = pts.repeat_interleave(reps, 0)
    gt = None if g is None else torch.full((len(x),), g, dtype=torch.float64)
    est = sky_inscatter(x, w.expand_as(x), gt, lambda p: sigma_t.expand(*p.shape[:-1], 3),
                        BOX, env, sampler, 4, 4, 8).reshape(3, reps, 3)
    for i, p in enumerate(pts):
        ref = sky_reference(p, w, g, sigma_t, env)
        z = (est[i].mean(0) - ref) / (est[i].std(0) / math.sqrt(reps))
        assert z.abs().max() < 5, (i, z)
        grad_est = torch.autograd.grad(est[i].mean(0).sum(), sigma_t, retain_graph=True)[0]
        grad_ref = torch.autograd.grad(ref.sum(), sigma_t)[0]
        per_rep = torch.stack([torch.autograd.grad(est[i, k].sum(), sigma_t,
                                                   retain_graph=True)[0] for k in range(40)])
        se = per_rep.std(0) / math.sqrt(reps)
        assert ((grad_est - grad_ref).abs() < 5 * se + 1e-9).all(), (grad_est, grad_ref, se)


def test_uncollided_projection_matches_quadrature():
    """SH coefficients (degree 2) of the uncollided radiance in a homogeneous box lit by
    the sky and a sun: the sky part against the quadrature projection
    ``int T E(d) Y(-d) dd`` (|z| < 5, 300 independent estimates), the sun part exact
    (``T E_sun Y(-d_sun)``, 1e-6)."""
    torch.manual_seed(1)
    env = bright_spot_sky()
    sampler = EnvironmentDirectionSampler(env)
    sigma_t = torch.tensor([0.4, 1.0, 2.0], dtype=torch.float64)
    x = torch.tensor([[0.2, -0.3, 0.5]], dtype=torch.float64)
    medium = lambda p: sigma_t.expand(*p.shape[:-1], 3)  # noqa: E731
    reps = 300
    est = uncollided_sh(x.expand(reps, 3), medium, BOX, env, sampler, None, 2, 16, 8)
    _, t_exit, _ = ray_box_intersect(x.expand_as(QUAD), QUAD, BOX)
    rad = torch.exp(-sigma_t * t_exit[:, None]) * env.lookup(QUAD)
    ref = torch.einsum("nc,nk->ck", rad, sh_basis(-QUAD, 2)) * (4 * math.pi / len(QUAD))
    z = (est.mean(0) - ref) / (est.std(0) / math.sqrt(reps)).clamp_min(1e-12)
    assert z.abs().max() < 5, z
    sun = torch.nn.functional.normalize(torch.tensor([[0.3, 0.8, 0.2]], dtype=torch.float64))
    irr = torch.tensor([[5.0, 4.0, 3.0]], dtype=torch.float64)
    lights = DirectLights(torch.zeros(0, 3), torch.zeros(0, 3), sun, irr).to(torch.float64)
    black = EnvironmentMap(torch.zeros(8, 16, 3, dtype=torch.float64))
    only_sun = uncollided_sh(x, medium, BOX, black, EnvironmentDirectionSampler(black),
                             lights, 2, 4, 8)
    _, t_sun, _ = ray_box_intersect(x, sun, BOX)
    exact = (torch.exp(-sigma_t * t_sun) * irr)[..., None] * sh_basis(-sun, 2)[:, None, :]
    torch.testing.assert_close(only_sun, exact, rtol=1e-6, atol=1e-9)


def test_skies_sharing_shadow_rays_each_match_their_quadrature():
    """:func:`uncollided_sh_skies`: two skies (the bright-spot sky and a second spot elsewhere
    over a dimmer smooth sky) projected from one set of 16 shadow rays per point, half drawn
    like each sky. Each sky's coefficients against its own quadrature projection (|z| < 5,
    300 independent estimates: the multi-sample MIS weights keep each unbiased). With one
    sky, the same draws as :func:`uncollided_sh` give the same coefficients (float64:
    only the division's order differs, 1e-12)."""
    torch.manual_seed(2)
    first = bright_spot_sky()
    dim = torch.from_numpy(smooth_sky(16, 32)).double() * 0.3
    dim[11, 25] *= 400.0
    second = EnvironmentMap(dim)
    samplers = [EnvironmentDirectionSampler(first), EnvironmentDirectionSampler(second)]
    sigma_t = torch.tensor([0.4, 1.0, 2.0], dtype=torch.float64)
    x = torch.tensor([[0.2, -0.3, 0.5]], dtype=torch.float64)
    medium = lambda p: sigma_t.expand(*p.shape[:-1], 3)  # noqa: E731
    reps = 300
    est = uncollided_sh_skies(x.expand(reps, 3), medium, BOX, [first, second], samplers,
                              [None, None], 2, 16, 8)
    _, t_exit, _ = ray_box_intersect(x.expand_as(QUAD), QUAD, BOX)
    for env, coef in zip((first, second), est, strict=True):
        rad = torch.exp(-sigma_t * t_exit[:, None]) * env.lookup(QUAD)
        ref = torch.einsum("nc,nk->ck", rad, sh_basis(-QUAD, 2)) * (4 * math.pi / len(QUAD))
        z = (coef.mean(0) - ref) / (coef.std(0) / math.sqrt(reps)).clamp_min(1e-12)
        assert z.abs().max() < 5, z
    torch.manual_seed(3)
    (alone,) = uncollided_sh_skies(x.expand(4, 3), medium, BOX, [first], samplers[:1], [None],
                                   2, 16, 8)
    torch.manual_seed(3)
    own = uncollided_sh(x.expand(4, 3), medium, BOX, first, samplers[0], None, 2, 16, 8)
    torch.testing.assert_close(alone, own, rtol=1e-12, atol=1e-14)


def test_transport_target_closed_form_and_loss():
    """In a homogeneous box with a constant, isotropic in-scattered radiance S0 (the
    uncollided cache holding only band 0, the scattered field zero), the backward march
    gives ``albedo S0 (1 - exp(-sigma_t l))``, l the distance to the box along ``-w``:
    alpha compositing of a constant medium is exact for any strata, so 1e-6. The loss is
    the mean squared difference of the (zero) field and that target, in units of the
    radiance scale."""
    light = SHGridLightField(degree=1, resolution=4).double()
    light.bbox.copy_(BOX)
    light.radiance_scale.fill_(2.0)
    s0 = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    coef = torch.zeros(64, 3, 4, dtype=torch.float64)
    coef[..., 0] = s0 * math.sqrt(4 * math.pi)  # band 0: S0 / Y_00
    light.set_uncollided(coef)
    medium = homogeneous([0.3, 0.2, 0.1], [0.5, 1.0, 2.0], 0.5)
    torch.manual_seed(2)
    x = (torch.rand(200, 3, dtype=torch.float64) * 2 - 1) * 0.95
    w = sample_uniform_sphere(torch.rand(200, 2, dtype=torch.float64))
    target = scattered_target(light, medium, x, w, 7)
    _, length, _ = ray_box_intersect(x, -w, BOX)
    sigma_t = torch.tensor([0.8, 1.2, 2.1], dtype=torch.float64)
    albedo = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64) / sigma_t
    exact = albedo * s0 * (1 - torch.exp(-sigma_t * length[:, None]))
    torch.testing.assert_close(target, exact, rtol=1e-6, atol=1e-9)
    loss = transport_loss(light, medium, x, w, 7)
    torch.testing.assert_close(loss, torch.mean((exact / 2.0) ** 2))


class ParametricHomogeneous:
    """A homogeneous medium filling :data:`BOX` whose ``sigma_a``, ``sigma_s`` (3,) are
    tensors that may require gradients (float64), HG of ``g``."""

    def __init__(self, sigma_a: torch.Tensor, sigma_s: torch.Tensor, g: float):
        self.sigma_a, self.sigma_s, self.g = sigma_a, sigma_s, g

    def __call__(self, x: torch.Tensor) -> MediumProperties:
        lead = x.shape[:-1]
        sa, ss = self.sigma_a.expand(*lead, 3), self.sigma_s.expand(*lead, 3)
        return MediumProperties(sa, ss, ss / (sa + ss), torch.full(lead, self.g).to(x))


def test_unrolled_inscatter_is_zero_and_its_gradient_is_the_one_step_derivative():
    """The unrolled in-scattering's value is exactly zero, and its gradient with respect
    to the medium is unbiased for the derivative of the one-step scattered light's
    in-scattering ``int f(w . w') albedo S0 (1 - exp(-sigma_t l(x, w'))) dw'`` (a constant
    uncollided source S0 in band 0; alpha compositing of a constant medium is exact, so
    only the phase-sampled directions are random). The reference is that integral's
    autograd derivative by quadrature over 4e5 directions (error ~1e-6); the estimate's
    standard error comes from 16 independent repetitions, |z| < 5."""
    light = SHGridLightField(degree=1, resolution=4).double()
    light.bbox.copy_(BOX)
    s0 = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    coef = torch.zeros(64, 3, 4, dtype=torch.float64)
    coef[..., 0] = s0 * math.sqrt(4 * math.pi)
    light.set_uncollided(coef)
    g = 0.4
    x = torch.tensor([[0.3, -0.2, 0.1]], dtype=torch.float64)
    w = torch.nn.functional.normalize(torch.tensor([[0.2, 0.5, -1.0]], dtype=torch.float64), dim=-1)

    def params():
        return (torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64, requires_grad=True),
                torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True))

    torch.manual_seed(5)
    grads = []
    for _ in range(16):
        sa, ss = params()
        medium = ParametricHomogeneous(sa, ss, g)
        out = unrolled_inscatter(light, medium, x, w, medium(x).g, 2048, 5)
        assert torch.equal(out, torch.zeros_like(out))
        out.sum().backward()
        grads.append(torch.cat([sa.grad, ss.grad]))
    grads = torch.stack(grads)
    sa, ss = params()
    _, length, _ = ray_box_intersect(x.expand_as(QUAD), -QUAD, BOX)  # L(x, w') comes along w'
    weight = hg_phase(QUAD @ w[0], g) * 4 * math.pi / len(QUAD)
    exact = (weight[:, None] * ss / (sa + ss) * s0
             * (1 - torch.exp(-(sa + ss) * length[:, None]))).sum()
    exact.backward()
    ref = torch.cat([sa.grad, ss.grad])
    z = (grads.mean(0) - ref) / (grads.std(0) / math.sqrt(len(grads)))
    assert z.abs().max() < 5, (grads.mean(0), ref, z)
    assert (grads.std(0) < ref.abs()).all()  # the estimate is informative, not noise


def test_adjoint_target_marches_forward_along_w():
    """With a zero adjoint and a constant isotropic source ``Q`` (band 0) in a homogeneous
    medium, the adjoint's target is ``Q Y_00 (1 - exp(-sigma_t l)) / sigma_t`` with ``l``
    the distance to the box along ``+w`` (importance comes from downstream), exact for any
    strata (1e-6); the same with the direction reversed would fail."""
    q0 = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    zeros = torch.zeros(4, 4, 4, 3, dtype=torch.float64)
    source = zeros.clone()
    source[..., :] = q0
    one = torch.tensor(1.0, dtype=torch.float64)
    adjoint = SHGrid(zeros, zeros, 0, BOX, one)
    q = SHGrid(source, zeros, 0, BOX, one)
    medium = homogeneous([0.3, 0.2, 0.1], [0.5, 1.0, 2.0], 0.5)
    torch.manual_seed(3)
    x = (torch.rand(200, 3, dtype=torch.float64) * 2 - 1) * 0.95
    w = sample_uniform_sphere(torch.rand(200, 2, dtype=torch.float64))
    target = adjoint_target(adjoint, q, medium, x, w, 7)
    _, length, _ = ray_box_intersect(x, w, BOX)
    sigma_t = torch.tensor([0.8, 1.2, 2.1], dtype=torch.float64)
    exact = q0 / math.sqrt(4 * math.pi) * -torch.expm1(-sigma_t * length[:, None]) / sigma_t
    torch.testing.assert_close(target, exact, rtol=1e-6, atol=1e-9)


def test_medium_sensitivity_is_the_derivative_of_the_infinite_medium_solution():
    """In an infinite homogeneous isotropic medium with a constant uncollided source ``u``,
    the scattered light is ``c = sigma_s u / sigma_a`` and the adjoint of a constant
    ``Q`` is ``A = Q / sigma_a``; a photo loss ``Q V c`` then has the derivatives
    ``V Q u / sigma_a`` in sigma_s and ``-V Q sigma_s u / sigma_a^2`` in sigma_a. The
    surrogate's gradient, with those constant fields and the source normalised by
    ``q_scale``, must give them (1e-9: constant fields make the integral exact)."""
    sa = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64, requires_grad=True)
    ss = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    q0, u0, q_scale = torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64), 1.5, 4.0
    full = lambda v: v.detach().expand(4, 4, 4, 3).clone()  # noqa: E731  band 0 only
    # band-0 coefficients: L(w) = c Y_00 and A(w) = a Y_00, so int A L dw = a c
    c = ss * u0 / sa
    a = q0 / q_scale / sa
    one = torch.tensor(1.0, dtype=torch.float64)
    light = SHGrid(full(c), full(torch.full((3,), u0, dtype=torch.float64)), 0, BOX, one)
    adjoint = SHGrid(full(a), full(torch.zeros(3, dtype=torch.float64)), 0, BOX, one)
    medium = ParametricHomogeneous(sa, ss, 0.0)
    torch.manual_seed(1)
    pts = (torch.rand(64, 3, dtype=torch.float64) * 2 - 1)
    medium_sensitivity(adjoint, light, medium, pts, q_scale).backward()
    volume = 8.0
    with torch.no_grad():
        torch.testing.assert_close(ss.grad, volume * q0 * u0 / sa, rtol=1e-9, atol=0)
        torch.testing.assert_close(sa.grad, -volume * q0 * ss * u0 / sa ** 2, rtol=1e-9, atol=0)


def test_white_furnace_is_solved_by_the_transport_objective_alone():
    """White furnace: isotropic scattering without absorption (sigma_s = 2, optical
    half-width 2) under a constant sky c. The exact radiance is c everywhere, so the
    in-scattered radiance the photo objective uses, the sky's exact first scattering plus
    the learned scattered light, must be c at every point. Degree 0 holds isotropic
    in-scattering exactly. From zero (~0.3 c at the centre, error > 50%), 600 steps of the
    transport objective alone on an 8^3 grid come within a few per cent: measured over
    seeds 0-2 mean |error| 3.9-4.6%, signed mean -3.4% to -2.8%, 95th percentile 9-10%.
    The residual under-estimate is the method's own: it falls to -2.3% by 3000 steps
    (source iteration converges slowly in a white, thick medium) and the rest sits at the
    faces, where a trilinear grid clamped at its outer cell centres cannot follow the
    boundary layer (interior points: -0.6%). Bounds: mean |error| < 7%, signed mean in
    (-7%, +1%), 95th percentile < 15%."""
    torch.manual_seed(4)
    c = torch.tensor([1.0, 2.0, 0.5])
    env = EnvironmentMap(c.expand(8, 16, 3).clone())
    sampler = EnvironmentDirectionSampler(env)
    box = BOX.float()
    medium = GroundTruthMedium({"phase": "isotropic", "chromatic": True},
                               torch.zeros(4, 4, 4, 3), torch.full((4, 4, 4, 3), 2.0),
                               torch.zeros(4, 4, 4), box)
    sigma_t = lambda p: medium(p).sigma_t  # noqa: E731
    light = SHGridLightField(degree=0, resolution=8)
    light.bbox.copy_(box)
    centres = cell_centres(8, box).reshape(-1, 3)
    light.set_uncollided(uncollided_sh(centres, sigma_t, box, env, sampler, None, 0, 256, 16))
    probe = (torch.rand(300, 3) * 2 - 1) * 0.98
    w = sample_uniform_sphere(torch.rand(300, 2))
    with torch.no_grad():
        first = torch.stack([sky_inscatter(probe, w, None, sigma_t, box, env, sampler, 64, 0,
                                           32) for _ in range(4)]).mean(0)

    def error() -> torch.Tensor:
        with torch.no_grad():
            return (first + light.inscatter(probe, w, None)) / c - 1

    assert error().abs().mean() > 0.5
    opt = torch.optim.Adam(light.parameters(), lr=0.02)
    for _ in range(600):
        opt.zero_grad()
        x = box[0] + torch.rand(1024, 3) * 2
        transport_loss(light, medium, x, sample_uniform_sphere(torch.rand(1024, 2)),
                       16).backward()
        opt.step()
    err = error()
    assert err.abs().mean() < 0.07 and -0.07 < err.mean() < 0.01, (err.abs().mean(), err.mean())
    assert err.abs().quantile(0.95) < 0.15, err.abs().quantile(0.95)


@pytest.mark.parametrize("effects,parametrization", [
    ({"phase": "hg", "chromatic": True}, "scattering"),
    ({"phase": "hg", "chromatic": True}, "extinction"),
    ({"phase": "varying_hg", "chromatic": False}, "extinction"),
    ({"phase": "isotropic", "chromatic": True}, "extinction")])
def test_voxel_medium_composes_the_neural_heads_on_its_cells(effects, parametrization):
    """At the density's cell centres the composed voxels equal the heads of
    :class:`NeuralMedium` applied to the baked density and the (trilinearly upsampled)
    modulation; between them they interpolate linearly; grey media keep one sigma_t
    channel and an RGB albedo; g exists only for an HG phase."""
    torch.manual_seed(5)
    medium = VoxelMedium(effects, resolutions=[4], density_resolution=8,
                         parametrization=parametrization)
    medium.set_density(lambda p: 1 + p[:, 0] ** 2)
    start = medium(cell_centres(8, medium.bbox).reshape(-1, 3))  # sigma_t = rho, albedo 0.8
    torch.testing.assert_close(start.albedo, torch.full_like(start.albedo, 0.8))
    with torch.no_grad():
        medium.modulation.values.normal_(0, 0.3)
    centres = cell_centres(8, medium.bbox).reshape(-1, 3)
    ours, heads = medium(centres), NeuralMedium.forward(medium, centres)
    for key in ("sigma_a", "sigma_s", "albedo"):
        torch.testing.assert_close(getattr(ours, key), getattr(heads, key), rtol=1e-5,
                                   atol=1e-6)
    assert ours.sigma_t.shape[-1] == (3 if effects["chromatic"] else 1)
    assert (ours.g is None) == (effects["phase"] == "isotropic")
    mid = (centres[0] + centres[1]) / 2
    torch.testing.assert_close(medium(mid[None]).sigma_t[0],
                               (ours.sigma_t[0] + ours.sigma_t[1]) / 2, rtol=1e-5, atol=1e-6)


def test_coarse_to_fine_schedule_and_restarted_moments():
    assert [resolution_at(p, [4, 8, 16], [0.2, 0.5]) for p in (0, 0.19, 0.2, 0.7, 1)] == \
        [4, 4, 8, 16, 16]
    for bad in (([4, 8], []), ([4, 8], [0.5, 0.6]), ([4, 8, 16], [0.6, 0.5]), ([4, 8], [1.0])):
        with pytest.raises(NrtError):
            check_schedule(*bad, "budget.rte.medium_resolutions")
    grid = torch.nn.Parameter(torch.rand(4, 4, 4, 2))
    opt = torch.optim.Adam([grid], lr=0.1)
    grid.sum().backward()
    opt.step()
    before = grid.detach().clone()
    resample_parameter(grid, opt, 8)
    assert grid.shape == (8, 8, 8, 2) and grid not in opt.state
    torch.testing.assert_close(grid.mean(), before.mean(), rtol=1e-5, atol=1e-6)
    grid.grad = torch.ones_like(grid)
    opt.step()  # a fresh state of the new shape
    progress = [0.0]
    sched = decaying_lr(opt, 0.1, lambda: progress[0])
    for p, factor in ((0.5, 0.1 ** 0.5), (1.0, 0.1)):
        progress[0] = p
        sched.step()
        assert opt.param_groups[0]["lr"] == pytest.approx(0.1 * factor)



def test_a_ramp_scales_only_the_groups_marked_to_ramp_in():
    """``ramp_in`` rises linearly from 0 at its start to 1 after its length; with a ramp,
    ``decaying_lr`` multiplies the marked groups' decayed rate by it and leaves the others
    at the decay alone."""
    assert [ramp_in(p, 0.2, 0.4) for p in (0.0, 0.2, 0.4, 0.6, 0.9)] == \
        pytest.approx([0.0, 0.0, 0.5, 1.0, 1.0])
    assert (ramp_in(0.1, 0.2, 0.0), ramp_in(0.2, 0.2, 0.0)) == (0.0, 1.0)
    light, medium = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([{"params": [light], "lr": 0.1},
                            {"params": [medium], "lr": 0.2, "ramps_in": True}])
    progress = [0.0]
    sched = decaying_lr(opt, 0.1, lambda: progress[0], lambda: ramp_in(progress[0], 0.2, 0.4))
    for p in (0.1, 0.4, 0.8):
        progress[0] = p
        sched.step()
        decay = 0.1 ** p
        assert opt.param_groups[0]["lr"] == pytest.approx(0.1 * decay)
        assert opt.param_groups[1]["lr"] == pytest.approx(0.2 * decay * ramp_in(p, 0.2, 0.4))

@pytest.mark.slow  # ~25 s: two Mitsuba renders and a 3 x 3 supersampled reference
def test_first_scattering_image_matches_mitsuba_order_one():
    """The photo objective's rendering with the scattered light left out is the first
    scattering of the sky (MIS shadow rays) and of a sun (a point-like directional light)
    through a homogeneous chromatic box with HG g = 0.4. Mitsuba renders the same scene at
    order 1 (``max_depth = 2``) twice at 64 spp; nrt's image is averaged over 3 x 3
    sub-pixels (box filter) with 32 strata per ray and 16 + 16 shadow directions per
    stratum, its own Monte Carlo noise ~5x below Mitsuba's (measured), so the two-seed
    comparison of :mod:`mc_stats` applies: region means |z| < 5 and the structure ratio
    within its 5-sigma bound. The same renders reject nrt's image with g flipped (|z| up to
    75, ratio 17.6 in blue) and with 10% more sigma_s (z 6.5 and 11.5 in red and green)."""
    mi = select_variant()
    width = height = 24
    fov = 45.0
    intr = Intrinsics.from_fov_x(width, height, math.radians(fov))
    eye = np.array([0.8, 0.6, 3.6])
    c2w = look_at(eye, [0.0, 0.0, 0.0])
    sky = smooth_sky(16, 32)
    sun = np.array([0.36, 0.8, -0.48])
    sun /= np.linalg.norm(sun)
    irradiance = np.array([6.0, 5.0, 4.0])
    spec = make_spec(phase="hg", chromatic=True, order=1, g=0.4)
    n = 4
    grids = {"sigma_a": np.broadcast_to(np.float32([0.05, 0.1, 0.2]), (n, n, n, 3)).copy(),
             "sigma_s": np.broadcast_to(np.float32([0.6, 0.5, 0.4]), (n, n, n, 3)).copy(),
             "g": np.full((n, n, n), 0.4, np.float32)}
    scene = scene_dict(mi, spec, grids, sky, width, height, fov, 64)
    scene["sun"] = {"type": "directional", "direction": (-sun).tolist(),
                    "irradiance": {"type": "rgb", "value": irradiance.tolist()}}
    a, b = render_pair(mi, scene, c2w, 64)
    env = EnvironmentMap(torch.from_numpy(sky).double())
    sampler = EnvironmentDirectionSampler(env)
    medium = homogeneous([0.05, 0.1, 0.2], [0.6, 0.5, 0.4], 0.4)
    lights = DirectLights(torch.zeros(0, 3), torch.zeros(0, 3), torch.from_numpy(sun)[None],
                          torch.from_numpy(irradiance)[None]).to(torch.float64)

    def source(x, w, props):
        from nrt.physics.direct_light import direct_inscatter

        sigma_t = lambda p: medium(p).sigma_t  # noqa: E731
        return sky_inscatter(x, w, props.g, sigma_t, BOX, env, sampler, 16, 16, 16) + \
            direct_inscatter(x, w, props.g, lights, sigma_t, BOX, 16, jitter=True)

    torch.manual_seed(6)
    def image(o, d):
        flat_o, flat_d = o.reshape(-1, 3), d.reshape(-1, 3)
        with torch.no_grad():
            pix = render_view_rays(medium, flat_o, flat_d, env.lookup(flat_d), 32, source)
        return pix.reshape(o.shape)

    ref = footprint_average(image, c2w, intr, 3, chunk=3)
    check(compare(a, b, ref, atol=1e-6), "first scattering of sky and sun")
    assert SEEDS == (1, 2)
