"""benchmarks/medium_error.py: its table agrees with the metric the runs log, and its bins
partition the error (the docs quote its shares)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from benchmarks.medium_error import (
    depth_from_outside,
    error_row,
    gaussian_blur,
    scene_truth,
    truth_grids,
)
from nrt.data.grids import save_property_grids
from nrt.metrics import property_mse
from tests.conftest import ROOT

pytestmark = pytest.mark.unit


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


def test_depth_from_outside_is_the_nearest_face_s_optical_depth() -> None:
    """A uniform sigma_t = 2 on 8^3 cells of edge 0.25 (x), 0.5 (y) and 1 (z): a cell's
    depth is the least over the six faces of (cells before it + 1/2) x sigma_t x edge."""
    sigma_t = np.full((8, 8, 8), 2.0)
    depth = depth_from_outside(sigma_t, np.array([0.25, 0.5, 1.0]))
    i = np.arange(8)
    nearest = np.minimum(i, 7 - i) + 0.5
    z, y, x = np.meshgrid(nearest, nearest, nearest, indexing="ij")
    expected = np.minimum(np.minimum(2 * 0.25 * x, 2 * 0.5 * y), 2 * 1.0 * z)
    assert np.allclose(depth, expected)
    # a dense slab on the -x face: its own cells lie half a cell (12.5) deep, seen from -x;
    # the cell behind it is reached from +x (6.5 cells of 0.5) sooner than through it (25.25)
    sigma_t[:, :, 0] = 100.0
    edge = np.array([0.25, 1.0, 1.0])
    shielded = depth_from_outside(sigma_t, edge)
    assert np.isclose(shielded[4, 4, 0], 100 * 0.25 / 2)
    assert np.isclose(shielded[4, 4, 1], 6.5 * 2 * 0.25)


def test_gaussian_blur_keeps_constants_and_mass_and_spreads_by_sigma() -> None:
    constant = np.full((8, 9, 10, 3), 2.5)
    assert np.allclose(gaussian_blur(constant, 1.0), 2.5)  # replicate padding at the edges
    impulse = np.zeros((21, 21, 21, 2))
    impulse[10, 10, 10] = (1.0, 3.0)
    offsets = np.arange(21) - 10
    for sigma in (1.0, 1.5):
        blurred = gaussian_blur(impulse, sigma)
        assert np.allclose(blurred.sum((0, 1, 2)), (1.0, 3.0))  # mass kept away from edges
        for axis in range(3):
            others = tuple(a for a in range(3) if a != axis)
            profile = blurred[..., 0].sum(others)
            # the sampled Gaussian's variance is sigma^2 up to aliasing (exp(-2 pi^2 sigma^2),
            # < 3e-9 here) less the tail cut at 3 sigma, under 3 % of the variance
            assert np.isclose((profile * offsets ** 2).sum(), sigma ** 2, rtol=0.03)


@pytest.mark.slow  # 7-10 s: the benchmark run as a command
def test_the_mean_row_averages_the_runs_cell_by_cell(tmp_path) -> None:
    """Two runs off the truth by +e and -e each score mean(e^2); their mean is the truth
    (MSE 0): the command line reads the runs' exports and the dataset's ground truth."""
    rng = np.random.default_rng(1)
    truth = rng.gamma(1.0, 1.0, size=(8, 8, 8, 3))
    error = rng.normal(0.0, 0.1, size=truth.shape)
    g = np.zeros((8, 8, 8))
    bbox = np.array([[-1.0] * 3, [1.0] * 3])
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    save_property_grids(dataset / "ground_truth.npz",
                        {"sigma_a": 0 * truth, "sigma_s": truth, "g": g}, bbox)
    runs = []
    for sign in (1, -1):
        run = tmp_path / f"run{sign}"
        run.mkdir()
        save_property_grids(run / "medium_grids.npz",
                            {"sigma_a": 0 * truth, "sigma_s": truth + sign * error, "g": g}, bbox)
        runs.append(str(run))
    proc = subprocess.run([sys.executable, "-m", "benchmarks.medium_error", *runs, "--mean",
                           "--dataset", str(dataset)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, check=True)
    rows = {line.split(" | ")[0].strip("| "): float(line.split(" | ")[1])
            for line in proc.stdout.splitlines() if line.startswith("| ") and "MSE" not in line}
    # float32 files: the truth and the runs round to ~1e-7 relative, far under the 3 digits
    expected = 100 * np.mean(np.float32(error) ** 2)
    assert all(abs(rows[run] - expected) < 2e-3 for run in runs)
    assert rows["mean of the 2 runs"] < 1e-3


def test_a_scene_s_truth_from_its_spec_is_the_rendered_dataset_s(tiny_dataset) -> None:
    """``--scene``: the grids computed from the spec, with nothing rendered, are those nrt-data
    wrote beside the photos of the same scene and preset (float32 on disk)."""
    from_spec = scene_truth("default", "tiny")
    rendered = truth_grids(tiny_dataset)
    assert from_spec.keys() == rendered.keys()
    for name, grid in rendered.items():
        assert np.array_equal(np.float32(from_spec[name]), np.float32(grid)), name


@pytest.mark.slow  # 7-10 s: the benchmark run as a command
def test_floors_of_a_scene_need_no_run(tmp_path) -> None:
    """The truth on R^3 cells and back: a finer grid loses less (the default scene, tiny)."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.medium_error", "--scene", "default",
                           "--preset", "tiny", "--floor", "8", "--floor", "16"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120, check=True)
    floors = [float(line.split(" | ")[1]) for line in proc.stdout.splitlines()
              if line.startswith("| truth on")]
    assert len(floors) == 2 and floors[0] > floors[1] > 0
    bare = subprocess.run([sys.executable, "-m", "benchmarks.medium_error"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert bare.returncode == 2 and "--scene NAME" in bare.stderr
