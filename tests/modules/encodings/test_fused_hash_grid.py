"""The fused CPU hash grid (``fused=True``) against the PyTorch path: the encoding and the
table gradient on dense and hashed levels, the same bits on 1 and 2 threads, and the
PyTorch path where a gradient with respect to the points is needed or nothing can be built.

Tolerances. Both paths form the same products (weights ``(wx * wy) * wz``, ``w * table``
and ``grad * w``); only the order of the sums may differ. Forward: with |table| <= 1
(``init_scale=1``) and weights >= 0 summing to 1, reordering the 8-term sum moves a feature
by at most 2 * 7 * u * sum |w t| <= 14 u: 8.3e-7 in float32 (u = 2^-24), hence atol 1e-6;
1.6e-15 in float64, within the 1e-12 asked. Gradient: a row sums n <= 8 P terms
|grad * w|, so two orders differ by at most 2 n u S, S the row's sum of |grad * w| (the
PyTorch path's gradient for |grad|, weights being >= 0); float64 is held to 1e-12.
"""

import logging

import pytest
import torch
from omegaconf import OmegaConf

from nrt.cli.common import CONFIG_DIR
from nrt.modules.encodings import fused_hash_grid
from nrt.modules.encodings.hash_grid import HashGrid
from nrt.modules.fields.ea_field import EAField
from tests.conftest import built_or_skip, computed_by, without_compiler

pytestmark = pytest.mark.unit

GRIDS = {  # (levels, log2 table, base resolution, growth): all dense; dense then hashed
    "dense": (3, 12, 4, 1.5),
    "hashed": (6, 9, 3, 1.6),
}


@pytest.fixture(scope="module")
def ext():
    """The extension, or a skip saying why not."""
    return built_or_skip(fused_hash_grid.EXTENSION)


def grids(kind: str, dtype: torch.dtype) -> tuple[HashGrid, HashGrid]:
    """The same grid twice: PyTorch path, fused."""
    levels, log2, base, growth = GRIDS[kind]
    torch.manual_seed(0)
    plain = HashGrid(levels, 2, log2, base, growth, init_scale=1.0).to(dtype)
    fused = HashGrid(levels, 2, log2, base, growth, init_scale=1.0, fused=True).to(dtype)
    fused.load_state_dict(plain.state_dict())
    assert plain.dense[0] and (all(plain.dense) if kind == "dense" else not plain.dense[-1])
    return plain, fused


def points(n: int, dtype: torch.dtype) -> torch.Tensor:
    """Random points in [-0.25, 1.25]^3 (clamped onto the box) with 0, 1 and faces."""
    torch.manual_seed(1)
    x = torch.rand(n, 3, dtype=dtype) * 1.5 - 0.25
    x[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [-1.0, 2.0, 1.0]])
    return x


def fused_in_graph(out: torch.Tensor) -> bool:
    """Whether the fused kernels computed ``out``."""
    return computed_by(out, "FusedEncoding")


def table_grad(grid: HashGrid, x: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    grid.zero_grad()
    grid(x).backward(grad)
    return grid.table.grad.clone()


@pytest.mark.parametrize("kind", sorted(GRIDS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_encoding_and_table_gradient_match_the_pytorch_path(ext, kind, dtype):
    plain, fused = grids(kind, dtype)
    x = points(512, dtype).view(2, 256, 3)  # leading dimensions are kept
    want, got = plain(x), fused(x)
    assert got.shape == want.shape == (2, 256, plain.output_dim)
    assert fused_in_graph(got) and not fused_in_graph(want)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(got, want, rtol=0, atol=tol)

    grad = torch.randn_like(want)
    want_g, got_g = table_grad(plain, x, grad), table_grad(fused, x, grad)
    if dtype == torch.float64:
        torch.testing.assert_close(got_g, want_g, rtol=1e-12, atol=1e-12)
    else:
        bound = 2 * 8 * len(x.view(-1, 3)) * 2.0**-24 * table_grad(plain, x, grad.abs())
        assert ((got_g - want_g).abs() <= bound).all()
    assert got_g.abs().sum() > 0


def test_one_and_two_threads_give_the_same_bits(ext):
    _, fused = grids("hashed", torch.float32)
    x = points(4096, torch.float32)
    grad = torch.randn(len(x), fused.output_dim)
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            assert ext.parallel_threads() == n  # built with ATen's thread pool (OpenMP)
            runs.append((fused(x).detach(), table_grad(fused, x, grad)))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_a_gradient_with_respect_to_the_points_takes_the_pytorch_path(ext):
    plain, fused = grids("hashed", torch.float64)
    x = (points(32, torch.float64) * 0.8 + 0.1).requires_grad_(True)
    got = fused(x)
    assert not fused_in_graph(got)
    grad = torch.randn_like(got)
    (gx,) = torch.autograd.grad(got, x, grad)
    (want,) = torch.autograd.grad(plain(x), x, grad)
    assert torch.equal(gx, want) and gx.abs().sum() > 0
    with torch.no_grad():  # no graph: nothing needs d/dx, the fused path runs
        torch.testing.assert_close(fused(x), plain(x), rtol=0, atol=1e-12)


def test_what_the_fused_path_takes():
    table = torch.zeros(8, 2)
    x = torch.rand(4, 3)
    assert fused_hash_grid.fusable(x, table) and fused_hash_grid.fusable(x.double(),
                                                                         table.double())
    assert not fused_hash_grid.fusable(x.double(), table)  # the PyTorch path promotes
    assert not fused_hash_grid.fusable(x.half(), table.half())
    assert not fused_hash_grid.fusable(x.to("meta"), table.to("meta"))  # other devices
    assert not fused_hash_grid.fusable(x.requires_grad_(True), table)


def test_the_profiler_scope_surrounds_the_fused_call(ext):
    _, fused = grids("dense", torch.float32)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fused(points(64, torch.float32))
    assert "nrt/hash_grid" in {e.key for e in prof.key_averages()}


def test_without_a_compiler_one_warning_and_the_pytorch_path(monkeypatch, tmp_path, caplog):
    without_compiler(monkeypatch, tmp_path, fused_hash_grid)
    plain, fused = grids("hashed", torch.float32)
    x = points(64, torch.float32)
    with caplog.at_level(logging.WARNING, logger=fused_hash_grid.__name__):
        assert torch.equal(fused(x), plain(x)) and torch.equal(fused(x), plain(x))
    assert len(caplog.records) == 1 and "no C++ compiler found" in caplog.text
    assert "PyTorch path" in caplog.text and "no C++ compiler" in fused_hash_grid.unavailable()


def test_the_density_field_config_has_the_switch_on_and_the_class_off():
    cfg = OmegaConf.load(CONFIG_DIR / "model" / "density_field" / "hash_grid.yaml")
    assert cfg.hash_grid.fused is True
    assert not EAField(hash_grid={"levels": 2, "log2_table_size": 8}).encoding.fused
    assert EAField(hash_grid={"levels": 2, "log2_table_size": 8, "fused": True}).encoding.fused
