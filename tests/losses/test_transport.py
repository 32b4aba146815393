"""The transport objective and the adjoint coupling against closed forms and quadrature: the
transport target in a homogeneous box, the unrolled in-scattering's gradient, the adjoint's
target, the medium sensitivity of an infinite medium, and a white furnace solved by the
transport objective alone.

Monte Carlo estimates are compared with z-scores: the estimate's standard error comes from
its own independent repetitions, and |z| < 5 fails by chance with probability < 1e-6."""

from __future__ import annotations

import math

import pytest
import torch

from nrt.losses.adjoint import adjoint_target, medium_sensitivity
from nrt.losses.transport import scattered_target, transport_loss, unrolled_inscatter
from nrt.modules.fields.medium import GroundTruthMedium, MediumProperties
from nrt.modules.fields.sh_light_field import SHGrid, SHGridLightField
from nrt.physics.envmap import EnvironmentDirectionSampler, EnvironmentMap
from nrt.physics.phase import hg_phase, sample_uniform_sphere
from nrt.physics.sky_light import sky_inscatter, uncollided_sh
from nrt.physics.volume import cell_centres, ray_box_intersect
from tests.physics.homogeneous_box import BOX, QUAD, homogeneous

pytestmark = pytest.mark.unit


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
