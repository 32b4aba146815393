"""benchmarks/generative_sampling.py: every sampler is a valid nrt-sample setting, the
novelty distances find the nearest member (and skip a member's own truth where asked), and
the summary gives each sampler's mean and spread over its seeds."""

from __future__ import annotations

import pytest
import torch

from benchmarks.common import append_rows, read_table
from benchmarks.generative_sampling import FIELDS, SAMPLERS, nearest, summary
from nrt.evaluation.latent_gaussian import scott_bandwidth
from nrt.evaluation.sample import SampleSettings

pytestmark = pytest.mark.unit

EFFECTS = {"phase": "isotropic"}


def medium(sigma_t: float) -> dict[str, torch.Tensor]:
    """A constant 4^3 medium of extinction ``sigma_t`` (albedo 1/2)."""
    half = torch.full((4, 4, 4, 3), sigma_t / 2)
    return {"sigma_a": half, "sigma_s": half.clone(), "g": torch.zeros(4, 4, 4)}


@pytest.mark.parametrize("name", sorted(SAMPLERS))
def test_every_sampler_is_a_valid_nrt_sample_setting(name):
    settings = SampleSettings(**SAMPLERS[name])
    settings.check()
    bandwidth = settings.bandwidth_for(16, 16)
    if "bandwidth" not in SAMPLERS[name]:
        assert bandwidth is None
    elif SAMPLERS[name]["bandwidth"] == "scott":
        assert bandwidth == scott_bandwidth(16, 16)
    else:
        assert bandwidth == SAMPLERS[name]["bandwidth"]


def test_nearest_finds_the_closest_truth_and_can_skip_its_own():
    """sigma_t MSE x100 of a constant offset d is 100 d^2 (per channel, averaged); the
    media are float32, so 3.9 - 4.0 is exact to ~1e-6 relative."""
    truths = [medium(1.0), medium(2.0), medium(4.0)]
    assert nearest([medium(1.5), medium(3.9)], truths, EFFECTS) == pytest.approx(
        [25.0, 1.0], rel=1e-5)
    assert nearest(truths, truths, EFFECTS) == [0.0, 0.0, 0.0]
    assert nearest(truths, truths, EFFECTS, skip_self=True) == pytest.approx([100.0, 100.0,
                                                                             400.0])


def test_the_summary_gives_mean_and_spread_over_seeds(tmp_path):
    table = tmp_path / "sampling.csv"
    for seed, fid in ((0, 60.0), (1, 64.0)):
        row = {k: "1.0" for k in FIELDS}
        row.update({"label": "run_a", "run": "/runs/a", "sampler": "gaussian", "seed": seed,
                    "fid_train": fid})
        append_rows(table, FIELDS, [row])
    append_rows(table, FIELDS, [{**{k: "2.0" for k in FIELDS}, "label": "run_a",
                                 "run": "/runs/a", "sampler": "gaussian_t0.7", "seed": 0}])
    rows = read_table(table)
    assert len(rows) == 3 and set(rows[0]) == set(FIELDS)
    text = summary(rows).splitlines()
    assert len(text) == 4
    assert "| run_a | gaussian | 2 | 62.0 ± 2.8 | 1.0 ± 0.0 |" in text[2]
    assert text[3].startswith("| run_a | gaussian_t0.7 | 1 | 2.0 | 2.0 |")
