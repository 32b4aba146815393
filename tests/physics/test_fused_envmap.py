"""The fused CPU environment-map kernels (``fused_lookups=true``, :mod:`nrt.physics.fused_envmap`)
against the PyTorch path: the bilinear lookup, the sampler's density and its draws, on random
directions, the poles and the seam of the map; the PyTorch path where a gradient is needed,
where the switch is off or where nothing can be built.

Tolerances. Both paths form every value operation by operation in the same dtype, except
atan2 and acos, whose scalar (C library) and vectorised (PyTorch) forms are each within
1 ulp of the exact value, so u and v differ by at most 2 ulp(1) = 2 eps after their
divisions and the subtraction of floor(u) (a few more ulp: 8 eps allowed). The lookup is
bilinear and continuous (across the seam too, the columns wrapping around), with slope at
most W max|E| in u and (H - 1) max|E| in v, so values differ by at most 8 eps (W + H) max|E|.
The density is constant on cells: it agrees wherever u W and v (H - 1) + 1/2 lie more than
that shift from a cell boundary. The draws search the same cumulative table for the same
numbers and take sin, cos and sqrt in float64 before rounding to float32: at most one
float32 ulp apart (|d| <= 1, so 2^-24 absolute).
"""

import logging
import math

import pytest
import torch

from nrt.physics import fused_envmap, fused_lookup
from nrt.physics.envmap import EnvironmentDirectionSampler, EnvironmentMap, direction_to_uv
from tests.conftest import built_or_skip, without_compiler
from tests.physics.homogeneous_box import bright_spot_sky

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def ext():
    """The extension, or a skip saying why not."""
    return built_or_skip(fused_envmap.EXTENSION)


@pytest.fixture()
def switch():
    """Sets the switch for one test (``switch(on)``), restoring it after."""
    before = fused_lookup.fused_lookups()
    yield fused_lookup.use_fused_lookups
    fused_lookup.use_fused_lookups(before)


def directions(n: int, dtype: torch.dtype) -> torch.Tensor:
    """Random unit directions with the poles, the seam (u = 0 from both sides) and the
    axes among them."""
    torch.manual_seed(5)
    d = torch.nn.functional.normalize(torch.randn(n, 3, dtype=dtype), dim=-1)
    d[:8] = torch.tensor([[0, 1, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1], [1, 0, 0],
                          [-1, 0, 0], [1e-9, 0.5, -0.8], [-1e-9, 0.5, -0.8]], dtype=dtype)
    return torch.nn.functional.normalize(d, dim=-1)


def both(switch, f):
    """``f()`` by the PyTorch path, then by the kernels."""
    switch(False)
    want = f()
    switch(True)
    return want, f()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("height", "width"), [(16, 32), (64, 128), (3, 2)])
def test_lookup_matches_the_pytorch_path(ext, switch, dtype, height, width):
    torch.manual_seed(0)
    env = EnvironmentMap(torch.rand(height, width, 3, dtype=dtype) * 10)
    d = directions(20000, dtype).view(4, 5000, 3)  # leading dimensions are kept
    want, got = both(switch, lambda: env.lookup(d))
    eps = torch.finfo(dtype).eps
    assert got.shape == want.shape and got.dtype == want.dtype == dtype
    bound = 8 * eps * (width + height) * env.radiance.abs().max()
    assert (got - want).abs().max() <= bound
    # the map's dtype decides: float64 directions in a float32 map are looked up in float32
    want, got = both(switch, lambda: EnvironmentMap(env.radiance.float()).lookup(d.double()))
    assert got.dtype == want.dtype == torch.float32


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_density_matches_the_pytorch_path_off_the_cell_boundaries(ext, switch, dtype):
    sampler = EnvironmentDirectionSampler(bright_spot_sky())
    d = directions(50000, dtype)
    want, got = both(switch, lambda: sampler.pdf(d))
    assert got.dtype == want.dtype == dtype and got.shape == (50000,)
    u, v = direction_to_uv(d.double())
    shift = 8 * torch.finfo(dtype).eps * max(sampler.width, sampler.height)
    col, row = u * sampler.width, v * (sampler.height - 1) + 0.5
    clear = ((col - col.round()).abs() > shift) & ((row - row.round()).abs() > shift)
    assert clear.float().mean() > 0.99 and torch.equal(got[clear], want[clear])


def test_draws_match_the_pytorch_path(ext, switch):
    sampler = EnvironmentDirectionSampler(bright_spot_sky())
    want, got = both(switch, lambda: sampler.sample(100000, torch.Generator().manual_seed(2)))
    assert got.dtype == want.dtype == torch.float32 and got.shape == (100000, 3)
    assert (got - want).abs().max() <= 2.0**-24


def test_draws_find_the_cell_a_binary_search_finds(ext, switch):
    """Uniform numbers on the cumulative table's entries, just below and above them, at 0
    and just below 1 land in the cell of ``torch.searchsorted(right=True)``: the kernel
    starts from a guide table and steps to the same cell."""
    sampler = EnvironmentDirectionSampler(bright_spot_sky())
    cdf = sampler.cdf
    first = torch.cat([cdf, torch.nextafter(cdf, torch.zeros(())),
                       torch.nextafter(cdf, torch.ones(())),
                       torch.tensor([0.0, 1.0 - 2.0**-53])]).clamp(0.0, 1.0 - 2.0**-53)
    xi = torch.stack([first, torch.full_like(first, 0.5), torch.full_like(first, 0.5)], -1)
    switch(True)
    got = fused_envmap.fused_env_sample(cdf, sampler.cos_top, sampler.cos_bottom,
                                        sampler.width, xi)
    cell = torch.searchsorted(cdf, first, right=True).clamp_max(len(cdf) - 1)
    u, v = direction_to_uv(got.double())
    assert torch.equal((u * sampler.width).floor().long(), cell % sampler.width)
    # the row's polar middle (xi_1 = 1/2) rounds to the cell's own row
    assert torch.equal((v * (sampler.height - 1)).round().long(), cell // sampler.width)


def test_the_fused_sampler_is_unbiased(ext, switch):
    """With the kernels on, ``E(d) / pdf(d)`` over the sampler's draws estimates the sky's
    integral: |z| < 5 against a quadrature of the lookup (as the PyTorch path's test in
    test_envmap.py: fails by chance with probability < 1e-6)."""
    switch(True)
    env = bright_spot_sky()
    sampler = EnvironmentDirectionSampler(env)
    quad = directions(400_000, torch.float64)
    exact = env.lookup(quad).mean(0) * 4 * math.pi
    d = sampler.sample(400_000, torch.Generator().manual_seed(3)).double()
    est = env.lookup(d) / sampler.pdf(d).unsqueeze(-1)
    # the quadrature of 4e5 random directions has its own error: both in the z-score
    var = est.var(0) / len(d) + (env.lookup(quad) * 4 * math.pi).var(0) / len(quad)
    z = (est.mean(0) - exact) / var.sqrt()
    assert z.abs().max() < 5, z


def test_one_and_two_threads_give_the_same_bits(ext, switch):
    switch(True)
    env, sampler = bright_spot_sky(), EnvironmentDirectionSampler(bright_spot_sky())
    d = directions(30000, torch.float32)
    threads, out = torch.get_num_threads(), []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            out.append((env.lookup(d), sampler.pdf(d),
                        sampler.sample(30000, torch.Generator().manual_seed(1))))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(*out, strict=True))


def test_directions_that_need_a_gradient_take_the_pytorch_path(ext, switch):
    switch(True)
    env = EnvironmentMap(torch.rand(8, 16, 3))
    d = directions(100, torch.float32).requires_grad_(True)
    env.lookup(d).sum().backward()
    assert d.grad is not None and d.grad.abs().sum() > 0


def test_without_a_compiler_one_warning_and_the_pytorch_path(monkeypatch, tmp_path, caplog,
                                                              switch):
    without_compiler(monkeypatch, tmp_path, fused_envmap)
    env, d = bright_spot_sky(), directions(64, torch.float64)
    switch(True)
    with caplog.at_level(logging.WARNING, logger=fused_envmap.__name__):
        first, second = env.lookup(d), env.lookup(d)
    switch(False)
    assert torch.equal(first, env.lookup(d)) and torch.equal(second, first)
    assert len(caplog.records) == 1 and "no C++ compiler found" in caplog.text
