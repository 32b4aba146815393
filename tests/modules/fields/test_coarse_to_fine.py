"""Coarse-to-fine grids: the resolution schedule and its checks, a resampled parameter with
restarted moments, the decaying rate and the ramp of marked groups."""

from __future__ import annotations

import pytest
import torch

from nrt.errors import NrtError
from nrt.modules.fields.coarse_to_fine import (
    check_schedule,
    decaying_lr,
    ramp_in,
    resample_parameter,
    resolution_at,
)

pytestmark = pytest.mark.unit


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
