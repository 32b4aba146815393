"""Grid lookups split into one batch per thread: the same values, the same gradients up to
the rounding of their sum over batches, and the same lookup as an independent trilinear
interpolation."""

import pytest
import torch

from nrt.physics.volume import SPLIT_LOOKUPS_FROM, lookup_batches, sample_grid

pytestmark = pytest.mark.unit

BBOX = torch.tensor([[-1.0, -0.5, -1.0], [1.0, 1.5, 0.5]])


def trilinear(grid: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Cell-centred, edge-clamped trilinear interpolation of ``grid`` (Nz, Ny, Nx, C) at
    ``points`` (N, 3) of :data:`BBOX`, written out corner by corner in float64."""
    size = torch.tensor(grid.shape[2::-1], dtype=torch.float64)  # (Nx, Ny, Nz)
    u = ((points.double() - BBOX[0]) / (BBOX[1] - BBOX[0]) * size - 0.5)
    u = torch.minimum(u.clamp_min(0), size - 1)
    lo = u.floor().long()
    hi = torch.minimum(lo + 1, size.long() - 1)
    f = u - lo
    out = 0
    for corner in range(8):
        pick = [(corner >> axis) & 1 for axis in range(3)]
        idx = [hi[:, a] if pick[a] else lo[:, a] for a in range(3)]
        w = torch.prod(torch.stack([f[:, a] if pick[a] else 1 - f[:, a] for a in range(3)]), 0)
        out = out + w[:, None] * grid.double()[idx[2], idx[1], idx[0]]
    return out


def test_a_lookup_is_trilinear_interpolation_between_cell_centres():
    torch.manual_seed(0)
    grid = torch.rand(5, 6, 7, 3)
    points = torch.rand(SPLIT_LOOKUPS_FROM + 6, 3) * 1.2 * (BBOX[1] - BBOX[0]) + BBOX[0] - 0.1
    # float32 weights and sums of 8 values in [0, 1] against float64: a few ulps of float32
    # (~1e-7 relative) apart, well inside 1e-5; a wrong corner or weight is off by ~0.1
    torch.testing.assert_close(sample_grid(grid, points, BBOX).double(),
                               trilinear(grid, points), rtol=1e-5, atol=1e-6)


def test_batches_divide_the_points_and_never_exceed_the_threads():
    threads = torch.get_num_threads()
    assert lookup_batches(SPLIT_LOOKUPS_FROM - 2, torch.device("cpu")) == 1
    assert lookup_batches(SPLIT_LOOKUPS_FROM * 6, torch.device("meta")) == 1
    for n in (SPLIT_LOOKUPS_FROM, SPLIT_LOOKUPS_FROM * 6 + 1, 5 * 7 * 11 * 13 * 16):
        b = lookup_batches(n, torch.device("cpu"))
        assert 1 <= b <= threads and n % b == 0


@pytest.mark.parametrize("threads", [2, 3, 4])
def test_a_split_lookup_gives_the_values_bit_for_bit_and_the_gradient_to_rounding(threads):
    torch.manual_seed(1)
    grid = torch.rand(8, 8, 8, 5, dtype=torch.float32, requires_grad=True)
    points = torch.rand(300, 60, 3) * 2.4 - 1.2  # 18,000 points, some outside the box
    weights = torch.rand(300, 60, 5)
    before = torch.get_num_threads()
    results = []
    try:
        for t in (1, threads):
            torch.set_num_threads(t)
            assert lookup_batches(points[..., 0].numel(), points.device) == t
            grid.grad = None
            values = sample_grid(grid, points, BBOX)
            (values * weights).sum().backward()
            results.append((values.detach(), grid.grad.clone()))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(results[0][0], results[1][0])
    # a cell's gradient sums ~18,000 * 8 / 512 = 281 terms of size <= 1: float32 sums in
    # another order differ by a few ulps of the total (~1e-5 relative)
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-5, atol=1e-4)
