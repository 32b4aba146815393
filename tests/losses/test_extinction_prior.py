"""The extinction prior of split stage 2 (nrt/losses/extinction_prior.py) against closed
forms: plain, it is the mean extinction; with a saturation s each voxel costs
``s log(1 + sigma_t / s)``, which is sigma_t to first order below s, and whose gradient
with respect to the exponent t (``sigma_t = rho exp(t)``) is ``s sigma_t / (s + sigma_t)``,
never above s. A saturation that is not a positive number is refused naming its key, and
the config's key reaches the unit the stage builds."""

import math

import hydra
import pytest
import torch

from nrt.errors import ConfigError
from nrt.losses.extinction_prior import ExtinctionPrior
from nrt.losses.objective import WeightSchedule
from tests.conftest import compose_config

pytestmark = pytest.mark.unit


def prior(saturation: float | None = None) -> ExtinctionPrior:
    return ExtinctionPrior("extinction_prior", WeightSchedule(1.0), saturation=saturation)


def test_the_plain_prior_is_the_mean_extinction():
    sigma_t = torch.rand(4, 4, 4, 3, dtype=torch.float64) * 5
    torch.testing.assert_close(prior().penalty(sigma_t), sigma_t.mean())


def test_a_saturated_prior_is_s_log1p_and_linear_well_below_s():
    s = 0.5
    values = torch.tensor([0.0, 0.01, 0.2, 1.0, 5.0, 50.0], dtype=torch.float64)
    expect = [s * math.log1p(v / s) for v in values.tolist()]
    for v, e in zip(values, expect, strict=True):
        torch.testing.assert_close(prior(s).penalty(v.reshape(1)), torch.tensor(
            e, dtype=torch.float64))
    thin = torch.full((8,), 1e-3, dtype=torch.float64)  # relative gap ~ sigma_t / (2 s) = 1e-3
    assert float(prior(s).penalty(thin) / thin.mean()) == pytest.approx(1.0, abs=2e-3)


def test_its_gradient_in_the_exponent_is_at_most_s_and_pushes_thin_cells_harder():
    """d/dt of ``s log(1 + rho e^t / s)`` at t = 0 is ``s rho / (s + rho)``: per voxel (the
    loss is a mean over N voxels, so N times the gradient), never above s; against ten
    times the plain prior's weight a dense voxel (rho = 5) is pushed about as hard as by
    the plain prior (0.91x) and a thin one (rho = 0.2) 7.1x harder."""
    s, rho = 0.5, torch.tensor([0.01, 0.2, 1.0, 5.0, 500.0], dtype=torch.float64)
    t = torch.zeros_like(rho, requires_grad=True)
    prior(s).penalty(rho * t.exp()).backward()
    per_voxel = t.grad * rho.numel()
    torch.testing.assert_close(per_voxel, s * rho / (s + rho))
    assert float(per_voxel.max()) < s
    ratio = 10 * per_voxel / rho  # ten times the weight, against the plain prior's rho
    assert float(ratio[3]) == pytest.approx(10 * 0.5 / 5.5)
    assert float(ratio[1]) == pytest.approx(10 * 0.5 / 0.7)


@pytest.mark.parametrize("saturation", [0.0, -1.0, float("nan"), float("inf"), "high", True])
def test_a_saturation_that_is_no_positive_number_is_refused_naming_its_key(saturation):
    with pytest.raises(ConfigError, match=r"losses\.objectives\.extinction_prior\.saturation"):
        prior(saturation)


def test_the_configs_saturation_reaches_the_stages_prior():
    cfg = compose_config("train", ["preset=tiny", "init=none", "stage=rte",
                                   "losses.objectives.extinction_prior.saturation=0.5"])
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert model.objectives["extinction_prior"].saturation == 0.5
    default = compose_config("train", ["preset=tiny", "init=none", "stage=rte"])
    assert default.losses.objectives.extinction_prior.saturation is None
