"""benchmarks/medium_error.py: its table agrees with the metric the runs log, and its bins
partition the error (the docs quote its shares)."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.medium_error import error_row
from nrt.metrics import property_mse


def test_error_row_matches_the_logged_metric_and_its_bins_partition_the_error() -> None:
    rng = np.random.default_rng(0)
    truth = rng.gamma(1.0, 1.5, size=(8, 8, 8, 3))
    estimate = truth * rng.uniform(0.5, 1.5, size=truth.shape)
    estimate[0, 0, 0] = 2 * truth[0, 0, 0] + 5  # one inflated cell
    cells = error_row(estimate, truth, [0.0, 0.5, 2.0, 5.0, float("inf")])
    zeros = torch.zeros(8, 8, 8, 3, dtype=torch.float64)

    def grids(sigma_t: np.ndarray) -> dict[str, torch.Tensor]:
        return {"sigma_a": zeros, "sigma_s": torch.from_numpy(sigma_t), "g": zeros[..., 0]}

    logged = property_mse(grids(estimate), grids(truth), with_g=False)["sigma_t"]
    assert abs(float(cells[0]) - float(logged)) < 1e-3  # both x100; the cell has 3 digits
    assert 0 < float(cells[1]) < 1
    bins = [c.split(" / ") for c in cells[2:] if c != "-"]
    assert abs(sum(float(b[0]) for b in bins) - 1) < 0.01  # cell shares, rounded to 3 digits
    assert abs(sum(float(b[1]) for b in bins) - 1) < 0.03  # error shares, rounded to 2 digits
