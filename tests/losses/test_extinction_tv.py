"""The total-variation prior of split stage 2 (nrt/losses/extinction_tv.py) against closed
forms: forward differences are exact on a linear field, so a ramp's TV is its slope at any
resolution; a monotone step of height H across the box costs H / 2 per unit volume
(interface area 4 over volume 8) whether sharp or spread over cells; a flat field costs
nothing and keeps a finite gradient."""

import pytest
import torch

from nrt.losses.context import StepContext
from nrt.losses.extinction_tv import EPS, ExtinctionTV, total_variation
from nrt.losses.objective import WeightSchedule
from nrt.physics.volume import cell_centres

pytestmark = pytest.mark.unit

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def field(r: int, fn) -> torch.Tensor:
    """``fn(z, y, x)`` at the centres of r^3 cells of BOX (:func:`cell_centres`, the grid
    convention the medium uses), as (r, r, r, 1)."""
    x, y, z = cell_centres(r, BOX.double()).unbind(-1)
    return fn(z, y, x).unsqueeze(-1)


@pytest.mark.parametrize("r", [8, 16, 32])
def test_a_ramp_costs_its_slope_at_any_resolution(r):
    slope = torch.tensor([0.5, -1.5, 2.0], dtype=torch.float64)  # d/dz, d/dy, d/dx
    s = field(r, lambda z, y, x: 3 + slope[0] * z + slope[1] * y + slope[2] * x)
    expect = torch.sqrt(slope.square().sum() + EPS ** 2) - EPS
    torch.testing.assert_close(total_variation(s, BOX), expect)


@pytest.mark.parametrize("width", [0, 3])
def test_a_step_costs_its_height_over_two_sharp_or_spread(width):
    """A step of height H along x, sharp (one jump) or a linear ramp over ``width`` cells:
    on each of the (R - 1)^2 lines the jumps sum to H over cells of size h, so the mean over
    (R - 1)^3 cells is H / (h (R - 1)) (-> H / 2 as R grows), up to eps per cell."""
    r, height = 32, 4.0
    h = 2.0 / r
    ramp = max(width, 1) * h
    s = field(r, lambda z, y, x: height * ((x + ramp / 2) / ramp).clamp(0, 1))
    expect = height / (h * (r - 1))
    torch.testing.assert_close(total_variation(s, BOX, eps=0.0), torch.tensor(
        expect, dtype=torch.float64), rtol=1e-9, atol=0)


def test_channels_are_averaged_and_a_flat_field_has_zero_cost_and_finite_gradient():
    flat = torch.full((8, 8, 8, 3), 2.0, requires_grad=True)
    tv = total_variation(flat, BOX)
    tv.backward()
    assert float(tv) == 0.0 and torch.isfinite(flat.grad).all()
    rgb = torch.cat([field(8, lambda z, y, x, c=c: c * x) for c in (1.0, 2.0, 3.0)], -1)
    torch.testing.assert_close(total_variation(rgb, BOX),
                               total_variation(field(8, lambda z, y, x: 2.0 * x), BOX))


def test_noise_costs_more_than_the_smooth_field_it_sits_on():
    """What the prior is for: the same field with cell-to-cell noise of 5 % costs more,
    so descending it removes noise-like texture."""
    torch.manual_seed(0)
    smooth = field(32, lambda z, y, x: 1 + 0.5 * torch.cos(2 * x) * torch.cos(3 * y))
    noisy = smooth * (1 + 0.05 * torch.randn_like(smooth))
    assert float(total_variation(noisy, BOX)) > 1.5 * float(total_variation(smooth, BOX))


def test_the_objective_averages_the_stages_media():
    def media():
        return [Voxels(field(8, lambda z, y, x: x)), Voxels(field(8, lambda z, y, x: 3 * x))]

    class Voxels:
        def __init__(self, s):
            self.extinction, self.bbox = s, BOX

    unit = ExtinctionTV("extinction_tv", WeightSchedule(1.0))
    expect = (total_variation(field(8, lambda z, y, x: x), BOX)
              + total_variation(field(8, lambda z, y, x: 3 * x), BOX)) / 2
    torch.testing.assert_close(unit.loss({}, StepContext([], voxels=media)), expect)
