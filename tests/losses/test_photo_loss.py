"""The photo objective's estimator: one jittered ray per pixel squares its Monte Carlo error
into the loss (a pull toward media whose radiance varies less inside a pixel), twin rays
through the same pixel do not; and the twin rays the data module draws for it."""

from __future__ import annotations

import math

import hydra
import pytest
import torch

from nrt.data.datamodule import RandomRays
from nrt.data.dataset import load_dataset
from nrt.losses.photo import photo_loss
from tests.conftest import compose_config

pytestmark = pytest.mark.unit

PIXELS = 200_000


def pixel_samples(mean: torch.Tensor, spread: torch.Tensor, g: torch.Generator
                  ) -> torch.Tensor:
    """One estimate per pixel of a pixel whose radiance varies linearly across its
    footprint: uniform on [mean - sqrt(3) spread, mean + sqrt(3) spread] (mean ``mean``,
    standard deviation ``spread``), as one jittered ray sees a gradient inside a pixel."""
    u = torch.rand(PIXELS, 3, generator=g, dtype=torch.float64)
    return mean + spread * math.sqrt(12.0) * (u - 0.5)


@pytest.fixture
def pixels():
    g = torch.Generator().manual_seed(0)
    mean = torch.rand(PIXELS, 3, generator=g, dtype=torch.float64)
    truth = mean + 0.05 * torch.randn(PIXELS, 3, generator=g, dtype=torch.float64)
    return g, mean, truth


@pytest.mark.parametrize("twins", [False, True])
def test_the_twin_product_is_unbiased_for_the_square_of_the_pixel_mean_error(pixels, twins):
    """Linear tonemap, where the box-filtered pixel is exactly the mean of the estimates.
    E[(a - p)^2] = (m - p)^2 + s^2 for one estimate a, E[(a - p)(b - p)] = (m - p)^2 for two
    independent ones. The tolerance is five standard errors of the loss, a mean over
    PIXELS x 3 independent terms whose spread is measured from the same draws."""
    g, mean, truth = pixels
    spread = torch.full_like(mean, 0.1)
    a = pixel_samples(mean, spread, g)
    b = pixel_samples(mean, spread, g) if twins else None
    loss = photo_loss(a, truth, 1.0, "linear", b)
    terms = (a - truth) * (b - truth) if twins else (a - truth) ** 2
    standard_error = terms.std() / math.sqrt(terms.numel())
    expected = torch.mean((mean - truth) ** 2) + (0.0 if twins else 0.1 ** 2)
    assert abs(float(loss - expected)) < 5 * float(standard_error)
    assert float(standard_error) < 0.1 ** 2 / 50  # the two cases are told apart


@pytest.mark.parametrize("tonemap", ["linear", "log"])
def test_only_the_single_ray_square_pulls_a_pixel_toward_uniform(pixels, tonemap):
    """The pixel's mean, the only thing a photo records, does not depend on the spread of
    radiance inside the pixel, so its expected gradient on that spread is 0 for the twins
    and 2 s (linear) for the single ray's square: the blur the twins remove. In log space
    the twins keep a second-order remainder (the tonemap of a mean is not the mean of the
    tonemap) far below the single ray's pull."""
    g, mean, truth = pixels
    pulls = {}
    for twins in (False, True):
        spread = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
        a = pixel_samples(mean, spread, g)
        b = pixel_samples(mean, spread, g) if twins else None
        photo_loss(a, mean, 1.0, tonemap, b).backward()
        pulls[twins] = float(spread.grad)
    if tonemap == "linear":
        # d/ds of E[(a - m)^2] = d/ds s^2; the twins' gradient has mean 0 and a standard
        # error below 2 s / sqrt(PIXELS x 3) x a few: 1e-3 is > 5 of them
        assert pulls[False] == pytest.approx(2 * 0.1, rel=0.02)
        assert abs(pulls[True]) < 1e-3
    else:
        assert pulls[False] > 0.05 and abs(pulls[True]) < 0.1 * pulls[False]


def test_twin_rays_pass_through_their_first_rays_pixels(tiny_dataset):
    """Each twin leaves the same camera through the same pixel as its first ray, jittered
    independently, with the background of its own direction; and drawing twins leaves the
    batches' rays as they were without them."""
    data = load_dataset(tiny_dataset, "train")
    plain = next(iter(RandomRays(data, 256, 1, seed=3)))
    batch = next(iter(RandomRays(data, 256, 1, seed=3, twins=100)))
    for key, value in plain.items():
        torch.testing.assert_close(batch[key], value, rtol=0, atol=0)
    assert batch["twin_dirs"].shape == batch["twin_origins"].shape == (100, 3)
    torch.testing.assert_close(batch["twin_origins"], batch["origins"][:100], rtol=0, atol=0)
    intr = data.intrinsics
    camera = torch.cdist(batch["origins"][:100], data.c2w[:, :3, 3]).argmin(dim=1)
    rotation = data.c2w[camera, :3, :3]

    def pixel(dirs: torch.Tensor) -> torch.Tensor:
        d = (rotation.transpose(1, 2) @ dirs.unsqueeze(-1)).squeeze(-1)  # camera frame
        return torch.stack((intr.cx + intr.fx * d[:, 0] / -d[:, 2],
                            intr.cy - intr.fy * d[:, 1] / -d[:, 2]), -1)

    first, twin = pixel(batch["dirs"][:100]), pixel(batch["twin_dirs"])
    assert torch.equal(first.floor(), twin.floor())  # the same pixel (cx, cy: its corner grid)
    assert (first - twin).abs().max() > 0.1  # not the same point
    env = batch["env"][:100]
    for e, envmap in enumerate(data.envmaps):
        mask = env == e
        torch.testing.assert_close(batch["twin_background"][mask],
                                   envmap.lookup(batch["twin_dirs"][mask]).float())


@pytest.mark.parametrize(("overrides", "twins"), [
    (("stage=rte", "ablation=photo_twins"), 256),  # every photo ray of the tiny preset
    (("stage=rte", "budget.rte.photo_twins=100"), 100),
    (("stage=rte",), 0),  # the default: one ray per pixel
    (("stage=ea", "budget.rte.photo_twins=100"), 0),  # stage 1 has no photo objective
])
def test_the_config_gives_the_data_module_the_photo_objectives_twins(tiny_dataset, overrides,
                                                                      twins):
    cfg = compose_config("train", ["preset=tiny", *overrides])
    data = hydra.utils.instantiate(cfg.data, dataset_dir=str(tiny_dataset))
    data.setup()
    batch = next(iter(data.train_dataloader()))
    assert len(batch.get("twin_dirs", ())) == twins
