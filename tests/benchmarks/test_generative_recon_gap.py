"""benchmarks/generative_recon_gap.py: each set takes exactly the part it names from the
truth (or the floor) and keeps the rest of the reconstruction, the blur fit finds the blur
a medium holds, and the summary reports each set against the reconstructions."""

from __future__ import annotations

import pytest
import torch

from benchmarks.common import append_rows, read_table
from benchmarks.generative_recon_gap import (
    BLUR_FIELDS,
    FIELDS,
    SETS,
    band_from,
    band_rows,
    blur_rows,
    extinction,
    media_sets,
    summary,
    with_albedo_g,
)
from benchmarks.medium_error import gaussian_blur

pytestmark = pytest.mark.unit


def medium(sigma_t: torch.Tensor, albedo: float, g: float) -> dict[str, torch.Tensor]:
    """A medium of extinction ``sigma_t`` (N, N, N) in every channel, one albedo and g."""
    t = sigma_t[..., None].expand(*sigma_t.shape, 3).double()
    return {"sigma_a": (1 - albedo) * t, "sigma_s": albedo * t,
            "g": torch.full(sigma_t.shape, g, dtype=torch.float64)}


def ramp(n: int = 4) -> torch.Tensor:
    """Extinction 0, 1, 2, ... along x (cell 0 empty)."""
    return torch.arange(n, dtype=torch.float64).expand(n, n, n).clone()


def test_albedo_and_g_are_swapped_and_the_extinction_kept():
    truth, recon = medium(ramp(), 0.9, 0.5), medium(2 * ramp() + 0.5, 0.6, -0.2)
    mixed = with_albedo_g(recon, truth, recon)
    assert torch.allclose(extinction(mixed), extinction(recon))
    occupied = ramp() > 0
    assert torch.allclose((mixed["sigma_s"] / extinction(mixed))[occupied],
                          torch.tensor(0.9, dtype=torch.float64))
    # the truth is empty in cell x = 0: the reconstruction keeps its own albedo there
    assert torch.allclose((mixed["sigma_s"] / extinction(mixed))[~occupied],
                          torch.tensor(0.6, dtype=torch.float64))
    assert torch.equal(mixed["g"], recon["g"])
    assert torch.equal(with_albedo_g(recon, recon, truth)["g"], truth["g"])


def test_a_band_takes_only_its_cells_from_the_floor():
    truth = medium(ramp(), 0.8, 0.0)
    recon, floor = medium(torch.full((4, 4, 4), 7.0), 0.5, 0.3), medium(ramp() + 0.25, 0.8, 0)
    mixed = band_from(recon, floor, truth, (1.0, 3.0))
    inside = (ramp() >= 1) & (ramp() < 3)
    assert torch.equal(extinction(mixed)[inside], extinction(floor)[inside])
    assert torch.equal(extinction(mixed)[~inside], extinction(recon)[~inside])
    assert torch.equal(mixed["g"], recon["g"])


def test_every_set_is_built_with_a_medium_per_member():
    truths = [medium(ramp(), 0.8, 0.1), medium(2 * ramp(), 0.7, -0.1)]
    sets = media_sets(truths, truths, truths)
    assert tuple(sets) == SETS
    assert all(len(media) == 2 for media in sets.values())
    # a reconstruction equal to the truth makes every set the truth's extinction
    for media in sets.values():
        for m, t in zip(media, truths, strict=True):
            assert torch.allclose(extinction(m), extinction(t))


def test_the_blur_fit_finds_the_blur_a_medium_holds():
    torch.manual_seed(0)
    sigma_t = torch.rand(12, 12, 12) * 4
    truth = medium(sigma_t, 0.8, 0.0)
    blurred = torch.from_numpy(gaussian_blur(extinction(truth).numpy(), 1.5))
    held = {"sigma_a": 0.2 * blurred, "sigma_s": 0.8 * blurred, "g": truth["g"]}
    rows = blur_rows([truth], {"blurred": [held], "truth": [truth]}, "a", "/runs/a")
    for name, best in (("blurred", 1.5), ("truth", 0.0)):
        mine = [r for r in rows if r["medium"] == name]
        least = min(mine, key=lambda r: float(r["mse_sigma_t_x100"]))
        assert least["blur_cells"] == best
        assert float(least["mse_sigma_t_x100"]) == pytest.approx(0.0, abs=1e-8)


def test_band_shares_sum_to_one_and_ratios_compare_with_the_truth():
    """Extinction 0, 1, 2, 3 along x: the empty band is x = 0, thin none, mid x = 1, dense
    x = 2, 3 (truth: 1 / 6 of the extinction mid, 5 / 6 dense)."""
    truth = medium(ramp(), 0.8, 0.0)
    halo = medium(ramp() * 0.5 + 0.5, 0.8, 0.0)  # 0.5, 1, 1.5, 2: spread into x = 0
    rows = {(r["medium"], r["band"]): r for r in band_rows(
        [truth], {"truth": [truth], "halo": [halo]}, "a", "/runs/a")}
    assert float(rows[("truth", "mid")]["share_mean"]) == pytest.approx(1 / 6, abs=1e-4)
    assert float(rows[("truth", "dense")]["ratio_mean"]) == pytest.approx(1.0)
    assert float(rows[("halo", "empty")]["share_mean"]) == pytest.approx(0.5 / 5, abs=1e-4)
    assert float(rows[("halo", "dense")]["ratio_mean"]) == pytest.approx(3.5 / 5, abs=1e-4)
    assert rows[("halo", "empty")]["ratio_mean"] == ""  # the truth holds none there
    # the thin band [0, 0.5) holds only the empty cells x = 0 here
    assert rows[("halo", "thin")]["share_mean"] == rows[("halo", "empty")]["share_mean"]
    assert rows[("halo", "thin")]["ratio_mean"] == ""
    for name in ("truth", "halo"):
        assert sum(float(rows[(name, b)]["share_mean"])
                   for b in ("empty", "mid", "dense")) == pytest.approx(1.0, abs=1e-3)


def test_the_summary_reports_each_set_against_the_reconstructions(tmp_path):
    table, blur = tmp_path / "gap.csv", tmp_path / "blur.csv"
    for seed, (recon, dense) in enumerate(((62.0, 59.0), (64.0, 60.0))):  # changes -3, -4
        append_rows(table, FIELDS, [
            {"label": "a", "run": "/runs/a", "set": name, "seed": seed, "n": 16,
             "fid_train": fid, "fid_novel": fid - 10}
            for name, fid in (("recon", recon), ("recon_dense_from_floor", dense))])
    append_rows(blur, BLUR_FIELDS, [
        {"label": "a", "run": "/runs/a", "medium": "recon", "blur_cells": s,
         "mse_sigma_t_x100": mse} for s, mse in ((0.0, 15.0), (2.5, 6.5), (3.0, 7.0))])
    text = summary(read_table(table), read_table(blur)).splitlines()
    assert "| a | recon | 2 | 63.0 ± 1.4 | 53.0 ± 1.4 | +0.0 ± 0.0 | +0.0 ± 0.0 |" in text
    assert ("| a | recon_dense_from_floor | 2 | 59.5 ± 0.7 | 49.5 ± 0.7 | -3.5 ± 0.7 | "
            "-3.5 ± 0.7 |") in text
    assert "| a | recon | 15.00 | 6.50 at 2.5 |" in text
