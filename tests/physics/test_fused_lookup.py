"""The fused CPU grid lookup (``fused_lookups=true``) against the PyTorch path of
:func:`~nrt.physics.volume.sample_grid`: the same values bit for bit (inside, on the faces and
outside the box, on cubes and uneven grids), the grid's gradient, the same bits on 1 and 2
threads, and the PyTorch path where a gradient with respect to the points is needed, where
the switch is off or where nothing can be built.

Tolerances. The values are grid_sample's operation by operation, so they are held to
equality. The gradient forms the same products ``grad * w`` and sums them per cell in
another order (parts of the points, then the parts): two orders of n terms differ by at most
2 n u S, S the cell's sum of |grad * w| (the PyTorch path's gradient for |grad|, the weights
being >= 0), n <= 8 P; float64 is held to 1e-12 relative.

The march (``optical_depth`` through a :class:`~nrt.physics.volume.GridExtinction`,
:func:`~nrt.physics.fused_lookup.fused_march`): the same depths to float rounding (midpoint
and jittered strata with the same random offsets; rays that leave the box, stop inside it or
have empty segments; origins broadcast against directions as the shadow rays pass them), the
grid's gradient, the same bits on 1 and 2 threads, and the PyTorch path where a gradient with
respect to the rays is needed or the medium is not a grid. Each stratum's point and lookup are
formed operation by operation as the PyTorch path forms them, so every looked-up value is the
same; only the sum over the S strata runs in another order. Two orders of S non-negative
terms differ by at most 2 S u times their sum, so a depth differs by at most 2 S u depth. The
gradient sums n = 8 S N products ``grad * length / S * w`` per cell in another order: at most
2 n u times the cell's gradient for |grad|.
"""

import logging

import pytest
import torch

from nrt.callbacks import FusedLookups
from nrt.physics import fused_lookup
from nrt.physics.volume import GridExtinction, optical_depth, ray_box_intersect, sample_grid
from tests.conftest import built_or_skip, computed_by, without_compiler

pytestmark = pytest.mark.unit

BOX = torch.tensor([[-1.0, -0.5, -2.0], [1.0, 1.5, 0.0]])
"""A box that is neither centred nor a cube."""


@pytest.fixture(scope="module")
def ext():
    """The extension, or a skip saying why not."""
    return built_or_skip(fused_lookup.EXTENSION)


@pytest.fixture()
def fused():
    """The switch on for one test."""
    before = fused_lookup.fused_lookups()
    fused_lookup.use_fused_lookups(True)
    yield
    fused_lookup.use_fused_lookups(before)


def points(n: int, dtype: torch.dtype) -> torch.Tensor:
    """Random points in the box grown by a fifth each way (some outside), with its corners,
    a face and a cell centre."""
    torch.manual_seed(1)
    lo, hi = BOX[0].to(dtype), BOX[1].to(dtype)
    x = lo + (torch.rand(n, 3, dtype=dtype) * 1.4 - 0.2) * (hi - lo)
    x[:4] = torch.stack([lo, hi, torch.stack([lo[0], hi[1], (lo[2] + hi[2]) / 2]),
                         lo + (hi - lo) / 16])
    return x


def plain_and_fused(grid: torch.Tensor, x: torch.Tensor, grad: torch.Tensor,
                    box: torch.Tensor | None = None, fuses: bool = True):
    """(values, grid gradient) by the PyTorch path, then with the switch on (where
    ``fuses``, by the fused kernels); ``box``: :data:`BOX` in the points' dtype."""
    box = BOX.to(x.dtype) if box is None else box
    out = []
    for on in (False, True):
        fused_lookup.use_fused_lookups(on)
        g = grid.detach().clone().requires_grad_(True)
        values = sample_grid(g, x, box)
        assert fused_in_graph(values) == (on and fuses)
        values.backward(grad)
        out.append((values.detach(), g.grad))
    return out


def fused_in_graph(out: torch.Tensor) -> bool:
    """Whether the fused kernels computed ``out``."""
    return computed_by(out, "FusedLookup")


@pytest.mark.parametrize(("shape", "n"), [((8, 8, 8, 4), 3000), ((5, 7, 9, 3), 3000),
                                          ((4, 4, 4, 48), 3000), ((6, 5, 4, 2), 40000)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_are_the_pytorch_paths_and_the_gradient_matches(ext, fused, shape, n, dtype):
    """40000 points: the PyTorch path splits the lookup per thread and the kernel sums two
    partial gradients, so the orders differ there."""
    torch.manual_seed(0)
    grid = torch.randn(*shape, dtype=dtype)
    x = points(n, dtype).view(4, n // 4, 3)  # leading dimensions are kept
    grad = torch.randn(4, n // 4, shape[-1], dtype=dtype)
    (want, want_g), (got, got_g) = plain_and_fused(grid, x, grad)
    assert got.shape == want.shape == (4, n // 4, shape[-1]) and torch.equal(got, want)
    if dtype == torch.float64:
        torch.testing.assert_close(got_g, want_g, rtol=1e-12, atol=1e-12)
    else:
        (_, scale), _ = plain_and_fused(grid, x, grad.abs())
        assert ((got_g - want_g).abs() <= 2 * 8 * n * 2.0**-24 * scale).all()
    assert got_g.abs().sum() > 0


def test_a_float32_grid_at_float64_points_is_looked_up_in_float64(ext, fused):
    grid = torch.randn(6, 6, 6, 2)
    x = points(100, torch.float64)
    (want, _), (got, _) = plain_and_fused(grid, x, torch.ones(100, 2, dtype=torch.float64))
    assert got.dtype == torch.float64 and torch.equal(got, want)


def test_a_box_of_another_dtype_takes_the_pytorch_path(ext, fused):
    """The PyTorch path forms a float32 box's extent in float32; an inexact one shows it."""
    box = torch.tensor([[0.1, -0.3, -2.2], [0.7, 1.1, 0.05]])
    x = points(500, torch.float64) * 0.3
    (want, _), (got, _) = plain_and_fused(torch.randn(5, 5, 5, 2), x,
                                          torch.ones(500, 2, dtype=torch.float64), box,
                                          fuses=False)
    assert torch.equal(got, want)


def test_one_and_two_threads_give_the_same_bits(ext, fused):
    torch.manual_seed(0)
    grid = torch.randn(16, 16, 16, 4)
    x = points(40000, torch.float32)  # more points than one partial gradient holds
    grad = torch.randn(len(x), 4)
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(plain_and_fused(grid, x, grad)[1])
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_a_gradient_with_respect_to_the_points_takes_the_pytorch_path(ext, fused, monkeypatch):
    grid, box = torch.randn(6, 6, 6, 3, dtype=torch.float64), BOX.double()
    x = points(50, torch.float64).requires_grad_(True)
    got = sample_grid(grid, x, box)
    assert not fused_in_graph(got)
    (gx,) = torch.autograd.grad(got.sum(), x)
    assert gx.abs().sum() > 0
    calls = []
    monkeypatch.setattr(fused_lookup.FusedLookup, "apply",
                        lambda *a, apply=fused_lookup.FusedLookup.apply: calls.append(1) or
                        apply(*a))
    with torch.no_grad():  # no graph: nothing needs d/dx, the fused path runs
        assert torch.equal(sample_grid(grid, x, box), got.detach())
    assert calls == [1]


def test_off_by_default_and_the_callback_switches_it_for_the_run():
    assert not fused_lookup.fused_lookups()
    try:
        for end in ("teardown", "on_exception"):  # Lightning skips teardown after an error
            callback = FusedLookups(enabled=True)
            callback.setup(None, None, "fit")
            assert fused_lookup.fused_lookups()
            if end == "teardown":
                callback.teardown(None, None, "fit")
            else:
                callback.on_exception(None, None, RuntimeError("killed"))
            assert not fused_lookup.fused_lookups()
    finally:
        fused_lookup.use_fused_lookups(False)
    grid, x = torch.randn(4, 4, 4, 1), points(8, torch.float32)
    assert not fused_in_graph(sample_grid(grid.requires_grad_(True), x, BOX))


def test_without_a_compiler_one_warning_and_the_pytorch_path(monkeypatch, tmp_path, caplog,
                                                              fused):
    without_compiler(monkeypatch, tmp_path, fused_lookup)
    grid, x = torch.randn(4, 4, 4, 2), points(64, torch.float32)
    with caplog.at_level(logging.WARNING, logger=fused_lookup.__name__):
        first, second = sample_grid(grid, x, BOX), sample_grid(grid, x, BOX)
    fused_lookup.use_fused_lookups(False)
    assert torch.equal(first, sample_grid(grid, x, BOX)) and torch.equal(second, first)
    assert len(caplog.records) == 1 and "no C++ compiler found" in caplog.text
    assert "PyTorch path" in caplog.text and "no C++" in fused_lookup.EXTENSION.unavailable()


# ------------------------------------------------------------------ the march
def rays(n: int, k: int, dtype: torch.dtype):
    """Shadow-ray-like rays: ``n`` origins in the box (N, 1, 3), ``k`` directions each
    (N, K, 3), from t0 (a tenth of the way, or 0) to the box's exit or a point before it;
    the first ray's first segment empty (t1 < t0)."""
    torch.manual_seed(3)
    lo, hi = BOX[0].to(dtype), BOX[1].to(dtype)
    x = lo + torch.rand(n, 1, 3, dtype=dtype) * (hi - lo)
    d = torch.nn.functional.normalize(torch.randn(n, k, 3, dtype=dtype), dim=-1)
    _, t_exit, _ = ray_box_intersect(x.expand_as(d), d, BOX.to(dtype))
    t0 = torch.where(torch.rand(n, k) < 0.5, 0.1 * t_exit, torch.zeros_like(t_exit))
    t1 = torch.where(torch.rand(n, k) < 0.5, 0.6 * t_exit, t_exit)
    t1[0, 0] = t0[0, 0] - 0.1
    return x, d, t0, t1


def both_paths(grid: torch.Tensor, x, d, t0, t1, strata: int, jitter: bool, grad=None):
    """(depths, grid gradient) by the PyTorch path, then the fused kernel, the same seed
    before each (the jitter's offsets)."""
    out = []
    for on in (False, True):
        fused_lookup.use_fused_lookups(on)
        g = grid.detach().clone().requires_grad_(True)
        torch.manual_seed(7)
        depth = optical_depth(GridExtinction(g, BOX.to(x.dtype)), x, d, t0, t1, strata,
                              jitter)
        assert computed_by(depth, "FusedMarch") == on
        depth.backward(torch.ones_like(depth) if grad is None else grad)
        out.append((depth.detach(), g.grad))
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("jitter", [False, True])
def test_march_depths_are_the_pytorch_paths_to_rounding_and_so_is_the_gradient(
        ext, fused, dtype, jitter):
    torch.manual_seed(0)
    grid = torch.rand(5, 7, 9, 3, dtype=dtype) * 4  # sigma_t >= 0, an uneven grid
    x, d, t0, t1 = rays(300, 16, dtype)
    grad = torch.randn(300, 16, 3, dtype=dtype)
    (want, want_g), (got, got_g) = both_paths(grid, x, d, t0, t1, 16, jitter, grad)
    assert got.shape == want.shape == (300, 16, 3)
    assert torch.equal(got[0, 0], torch.zeros(3, dtype=dtype))  # the empty segment
    assert (want > 0).float().mean() > 0.9
    if dtype == torch.float64:
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(got_g, want_g, rtol=1e-12, atol=1e-12)
        return
    u = 2.0**-24
    assert ((got - want).abs() <= 2 * 16 * u * want).all()
    (_, scale), _ = both_paths(grid, x, d, t0, t1, 16, jitter, grad.abs())
    assert ((got_g - want_g).abs() <= 2 * 8 * 16 * 300 * 16 * u * scale).all()
    assert got_g.abs().sum() > 0


def test_a_direction_broadcast_over_points_is_the_suns_march(ext, fused):
    """The known lights' shadow rays pass one direction expanded over every point."""
    torch.manual_seed(0)
    grid = torch.rand(6, 6, 6, 1, dtype=torch.float64)
    x = BOX[0].double() + torch.rand(200, 3, dtype=torch.float64) * (BOX[1] - BOX[0]).double()
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64), dim=0)
    d = sun.expand_as(x)
    _, t1, _ = ray_box_intersect(x, d, BOX.double())
    (want, want_g), (got, got_g) = both_paths(grid, x, d, torch.zeros_like(t1), t1, 8, True)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got_g, want_g, rtol=1e-12, atol=1e-12)


def test_the_march_gives_the_same_bits_on_one_and_two_threads(ext, fused):
    torch.manual_seed(0)
    grid = torch.rand(16, 16, 16, 3)
    x, d, t0, t1 = rays(2000, 32, torch.float32)  # more strata than one partial holds
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(both_paths(grid, x, d, t0, t1, 16, True)[1])
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_a_gradient_with_respect_to_the_rays_or_a_medium_of_another_kind_takes_the_pytorch_path(
        ext, fused):
    grid = torch.rand(6, 6, 6, 3, dtype=torch.float64)
    x, d, t0, t1 = rays(20, 4, torch.float64)
    d = d.clone().requires_grad_(True)
    depth = optical_depth(GridExtinction(grid, BOX.double()), x, d, t0, t1, 8)
    assert not computed_by(depth, "FusedMarch")
    (gd,) = torch.autograd.grad(depth.sum(), d)
    assert gd.abs().sum() > 0
    with torch.no_grad():  # nothing needs d/d(rays): fused, the same depths
        fused_depth = optical_depth(GridExtinction(grid, BOX.double()), x, d, t0, t1, 8)
    torch.testing.assert_close(fused_depth, depth.detach(), rtol=1e-12, atol=1e-12)
    g = grid.clone().requires_grad_(True)
    plain = optical_depth(lambda p: GridExtinction(g, BOX.double())(p), x, d.detach(), t0, t1, 8)
    assert not computed_by(plain, "FusedMarch") and computed_by(plain, "FusedLookup")


def test_without_a_compiler_the_march_takes_the_pytorch_path(monkeypatch, tmp_path, fused):
    without_compiler(monkeypatch, tmp_path, fused_lookup)
    grid = torch.rand(4, 4, 4, 2, requires_grad=True)
    x, d, t0, t1 = rays(10, 4, torch.float32)
    depth = optical_depth(GridExtinction(grid, BOX), x, d, t0, t1, 8)
    assert not computed_by(depth, "FusedMarch") and not computed_by(depth, "FusedLookup")
    fused_lookup.use_fused_lookups(False)
    assert torch.equal(depth, optical_depth(GridExtinction(grid, BOX), x, d, t0, t1, 8))
