"""benchmarks/generative_oracle.py: a medium's figures against its truth, checked on media
whose answers are known (the truth itself; the truth blurred by a known width); the summary
row; bad arguments refused with status 2 before anything is rendered or written."""

from __future__ import annotations

import sys

import pytest
import torch

from benchmarks.common import append_rows, read_table
from benchmarks.generative_oracle import FIELDS, main, medium_stats, summary
from benchmarks.medium_error import gaussian_blur

pytestmark = pytest.mark.unit


def blob() -> dict[str, torch.Tensor]:
    """A 24^3 medium: a Gaussian puff peaking at sigma_t 6 (a dense core >= 2, thin edges,
    empty corners), albedo 0.8 in every channel."""
    axis = torch.linspace(-1, 1, 24, dtype=torch.float64)
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    sigma_t = (6.0 * torch.exp(-(x ** 2 + y ** 2 + z ** 2) / (2 * 0.3 ** 2)))[..., None]
    sigma_t = sigma_t.expand(24, 24, 24, 3)
    return {"sigma_a": 0.2 * sigma_t, "sigma_s": 0.8 * sigma_t,
            "g": torch.zeros(24, 24, 24, dtype=torch.float64)}


def test_the_truth_itself_holds_no_blur_and_no_bias():
    mean = (blob()["sigma_a"] + blob()["sigma_s"]).mean(-1)
    assert (mean >= 2).any() and ((mean > 1e-3) & (mean < 0.5)).any()  # both bands present
    stats = medium_stats(blob(), blob())
    assert stats["least_blur_mse"] == 0 and stats["least_blur_cells"] == 0
    assert stats["thin_ratio"] == pytest.approx(1) and stats["dense_ratio"] == pytest.approx(1)
    assert stats["dense_bias"] == 0


def test_a_blurred_truth_is_found_at_its_width_with_a_halo_and_deflated_core():
    truth = blob()
    sigma_t = (truth["sigma_a"] + truth["sigma_s"]).numpy()
    blurred = torch.from_numpy(gaussian_blur(sigma_t, 1.5))
    stats = medium_stats(truth, {"sigma_a": blurred, "sigma_s": torch.zeros_like(blurred),
                                 "g": truth["g"]})
    assert stats["least_blur_cells"] == 1.5 and stats["least_blur_mse"] < 1e-20
    # a blur moves extinction out of the core into its surroundings
    assert stats["thin_ratio"] > 1.2 and stats["dense_ratio"] < 0.98
    assert stats["dense_bias"] < 0


def test_the_summary_row(tmp_path):
    table = tmp_path / "oracle.csv"
    append_rows(table, FIELDS, [{
        "preset": "cpu", "member": 1, "prior": "0", "seed": 1, "sigma_t_start": 11.88,
        "sigma_t_end": 16.25, "psnr": "37.95", "train_s": 205.0, "least_blur_mse": 3.2,
        "least_blur_cells": 1.0, "thin_ratio": 6.54, "dense_ratio": 0.991,
        "dense_bias": -0.05, "floor_least_blur_cells": 1.0, "floor_thin_ratio": 7.3,
        "floor_dense_ratio": 0.96, "floor_dense_bias": -0.16, "run": "/runs/x"}])
    line = summary(read_table(table)).splitlines()[2]
    assert line == ("| cpu | 1 | 0 | 1 | 11.88 -> 16.25 | 37.95 | 3.20 (1.0; 1.0) | 6.5 (7.3) "
                    "| 0.991 (0.960) | -0.050 (-0.160) | 205 |")


@pytest.mark.parametrize("args, needle", [
    (["--members", "a"], "--members"),
    (["--members=-1"], "--members"),
    (["--priors", "1e-4,x"], "--priors"),
    (["--priors=-1"], "--priors"),
    (["--preset", "tiny", "--members", "0,4"], "members 0..3"),  # K = 4 at tiny
])
def test_bad_arguments_are_refused_with_status_2(tmp_path, monkeypatch, capsys, args, needle):
    monkeypatch.setenv("NRT_OUTPUT_DIR", str(tmp_path / "out"))
    monkeypatch.setattr(sys, "argv", ["generative_oracle", *args,
                                      "--table", str(tmp_path / "t.csv")])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2 and needle in capsys.readouterr().err
    assert not list(tmp_path.iterdir())

