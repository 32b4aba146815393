"""Hash encoding: indexing and interpolation against a direct per-point reference,
gradients against finite differences."""

import math

import pytest
import torch

from nrt.modules.encodings.hash_grid import PRIMES, HashGrid

pytestmark = pytest.mark.unit


def reference_encoding(grid: HashGrid, x: torch.Tensor) -> torch.Tensor:
    """Per-point, per-corner Python loop with instant-ngp's uint32 hash arithmetic."""
    table = grid.table.detach().double()
    out = torch.zeros(len(x), grid.output_dim, dtype=torch.float64)
    for p, point in enumerate(x.double().tolist()):
        for level, res in enumerate(grid.resolutions):
            offset = int(grid.offsets[level])
            pos = [c * res for c in point]
            base = [min(math.floor(c), res - 1) for c in pos]
            feat = torch.zeros(grid.features, dtype=torch.float64)
            for dx in (0, 1):
                for dy in (0, 1):
                    for dz in (0, 1):
                        v = (base[0] + dx, base[1] + dy, base[2] + dz)
                        if (res + 1) ** 3 <= grid.table_size:
                            row = v[0] + (res + 1) * (v[1] + (res + 1) * v[2])
                        else:
                            h = 0
                            for c, prime in zip(v, PRIMES, strict=True):
                                h ^= (c * prime) & 0xFFFFFFFF
                            row = h % grid.table_size
                        w = 1.0
                        for c, b, d in zip(pos, base, (dx, dy, dz), strict=True):
                            f = c - b
                            w *= f if d else 1 - f
                        feat += w * table[offset + row]
            out[p, level * grid.features:(level + 1) * grid.features] = feat
    return out


def test_matches_reference_dense_and_hashed_levels():
    torch.manual_seed(0)
    grid = HashGrid(levels=4, features=2, log2_table_size=10, base_resolution=4, growth=2.0,
                    init_scale=1.0)
    assert grid.dense[:2] == [True, True] and grid.dense[2:] == [False, False]
    x = torch.rand(64, 3)
    x[0] = torch.tensor([0.0, 1.0, 0.5])  # box faces: clamped into the last cell
    got = grid.double()(x.double())
    torch.testing.assert_close(got, reference_encoding(grid, x), rtol=1e-12, atol=1e-12)


def test_gradients_match_finite_differences():
    torch.manual_seed(1)
    grid = HashGrid(levels=3, features=2, log2_table_size=8, base_resolution=3, growth=1.7,
                    init_scale=1.0).double()
    x = (torch.rand(8, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    # Piecewise trilinear: smooth inside cells; eps 1e-6 stays inside one cell.
    assert torch.autograd.gradcheck(lambda p: grid(p), (x,), eps=1e-6, atol=1e-6)
    table_fn = lambda t: torch.func.functional_call(grid, {"table": t}, (x.detach(),))  # noqa: E731
    assert torch.autograd.gradcheck(table_fn, (grid.table.detach().clone().requires_grad_(),),
                                    eps=1e-6, atol=1e-6)
