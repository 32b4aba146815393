"""Where a recovered medium's sigma_t error sits: by the true extinction, against grid floors.

For each run folder (a stage-2 run's ``medium_grids.npz``, or an EA run's grey
``density_grid.npz`` taken as sigma_t in every channel) the sigma_t MSE x100 on the ground
truth's grid (over cells and RGB, as ``val/mse_sigma_t_x100``), then per bin of the true
extinction (its channel mean): the share of the cells, the share of the squared error, the
mean signed error (bias) and its rms; and the share of the error in *inflated* cells, where
the estimate exceeds twice the truth plus one (stage 1's spikes, docs/stage2.md). ``--floor
R`` adds the same row for the truth itself resampled to R^3 cells and back (trilinear): the
least error a medium on that grid can have, and where it sits. ``--by depth`` bins the
cells by their true optical depth from outside the box instead (:func:`depth_from_outside`:
the least, over the six axis directions, of the truth's extinction integrated from the box
face to the cell's centre): how deep the light and the cameras must reach to see a cell's
error. ``--blur S`` adds, for each run, the row of its extinction blurred after training by a
Gaussian of S cells of the truth's grid (:func:`gaussian_blur`): whether the fine texture
a run keeps is error or the truth's (docs/stage2.md). ``--mean`` adds the row of the runs'
extinctions averaged cell by cell (an ensemble, e.g. stage 2 under several seeds): how much
of each run's error is its own run's noise. The dataset is the one the first run's
``run.json`` names, or ``--dataset``; or ``--scene NAME``, a benchmark scene whose ground
truth is computed from its spec at ``--preset`` with nothing rendered (with ``--floor`` and
no run: the floors alone, in seconds).

    python -m benchmarks.medium_error RUN [RUN ...] [--floor 32] [--blur 0.5] [--mean] [--by
        extinction|depth] [--bins 0.5,2,5] [--dataset outputs/datasets/<name>]
    python -m benchmarks.medium_error --scene heldout3 --floor 16 --floor 32
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from benchmarks.common import SCENES, compose_train
from nrt.data.grids import load_property_grids, resample_grids
from nrt.data.media import medium_grids
from nrt.data.spec import resolve_scene
from nrt.physics.volume import resample_cells

BINS = {"extinction": "0.5,2,5", "depth": "1,3"}
"""Default inner bin edges: of the true sigma_t (per unit length), of the optical depth."""


def truth_grids(dataset: Path) -> dict[str, np.ndarray]:
    """The dataset's ground-truth property grids (and its ``bbox``) as float64 arrays."""
    grids = load_property_grids(dataset / "ground_truth.npz")
    return {k: np.asarray(v, dtype=np.float64) for k, v in grids.items()}


def scene_truth(scene: str, preset: str) -> dict[str, np.ndarray]:
    """The ground-truth grids (and ``bbox``) of the benchmark scene ``scene`` at ``preset``,
    from its spec (what ``nrt-data`` would write into ``ground_truth.npz``), as float64."""
    config = compose_train([f"preset={preset}", *SCENES[scene]]).scene
    spec = resolve_scene(OmegaConf.to_container(config, resolve=True))
    grids = medium_grids(spec)
    return {**{k: np.asarray(v, dtype=np.float64) for k, v in grids.items()},
            "bbox": np.asarray(spec["bbox"], dtype=np.float64)}


def depth_from_outside(sigma_t: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """Each cell's optical depth from outside the box, (Nz, Ny, Nx): the least over the six
    axis directions of ``sigma_t`` (Nz, Ny, Nx, per unit length) integrated from the box
    face to the cell's centre (half the cell's own), with ``cell`` the cell's edge lengths
    (x, y, z) in world units."""
    depths = []
    for axis, length in zip((2, 1, 0), cell, strict=True):  # x is the last array axis
        tau = sigma_t * length
        for flip in (False, True):
            t = np.flip(tau, axis) if flip else tau
            inward = np.cumsum(t, axis) - 0.5 * t
            depths.append(np.flip(inward, axis) if flip else inward)
    return np.min(depths, axis=0)


def run_extinction(run: Path, resolution: int) -> np.ndarray:
    """A run's sigma_t on ``resolution``^3 cells, (..., 3): the stage-2 export's, or the EA
    density broadcast over RGB."""
    if (run / "medium_grids.npz").exists():
        grids = resample_grids(load_property_grids(run / "medium_grids.npz"), resolution)
        return np.asarray(grids["sigma_a"] + grids["sigma_s"], dtype=np.float64)
    if (run / "density_grid.npz").exists():
        with np.load(run / "density_grid.npz") as data:
            density = torch.from_numpy(data["density"].astype(np.float32))[..., None]
        grey = resample_cells(density, resolution).clamp_min(0).double().numpy()
        return np.repeat(grey, 3, -1)
    raise SystemExit(f"{run} has neither medium_grids.npz (a stage-2 run) nor density_grid.npz "
                     "(an EA run); pass a run folder of nrt-train.")


def gaussian_blur(grid: np.ndarray, sigma: float) -> np.ndarray:
    """``grid`` (Nz, Ny, Nx, C) blurred per channel by a separable Gaussian of standard
    deviation ``sigma`` cells, truncated at 3 sigma and normalised to sum 1, the edges
    padded by replication (so a constant stays constant)."""
    radius = int(np.ceil(3 * sigma))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    kernel = torch.as_tensor(taps / taps.sum())
    field = torch.as_tensor(grid).permute(3, 0, 1, 2)[:, None]  # (C, 1, Nz, Ny, Nx)
    for axis in range(3):
        shape = [1, 1, 1, 1, 1]
        shape[2 + axis] = kernel.numel()
        pad = [0] * 6
        pad[2 * (2 - axis)] = pad[2 * (2 - axis) + 1] = radius
        field = torch.nn.functional.conv3d(torch.nn.functional.pad(field, pad, mode="replicate"),
                                           kernel.view(shape))
    return field[:, 0].permute(1, 2, 3, 0).numpy()


def _tensors(grids: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.asarray(v, np.float32)) for k, v in grids.items()}


def error_row(estimate: np.ndarray, truth: np.ndarray, edges: list[float],
              key: np.ndarray | None = None) -> list[str]:
    """Markdown cells: the MSE x100, the inflated cells' error share, then per bin of
    ``key`` (Nz, Ny, Nx; by default the true extinction's channel mean) its cell share,
    error share, bias and rms."""
    squared = ((estimate - truth) ** 2).mean(-1)
    total = squared.sum()
    true_mean = truth.mean(-1)
    key = true_mean if key is None else key
    inflated = (estimate.mean(-1) > 2 * true_mean + 1)
    cells = [f"{100 * squared.mean():.3f}", f"{squared[inflated].sum() / total:.2f}"]
    for lo, hi in itertools.pairwise(edges):
        inside = (key >= lo) & (key < hi)
        if not inside.any():
            cells.append("-")
            continue
        diff = (estimate - truth)[inside]
        cells.append(f"{inside.mean():.3f} / {squared[inside].sum() / total:.2f} / "
                     f"{diff.mean():+.3f} / {np.sqrt((diff ** 2).mean()):.3f}")
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--dataset", type=Path, default=None)
    parser.add_argument("--scene", choices=sorted(SCENES), default=None,
                        help="a benchmark scene: its ground truth from its spec, unrendered")
    parser.add_argument("--preset", default="cpu", help="the preset of --scene")
    parser.add_argument("--floor", type=int, action="append", default=[],
                        help="grid resolution R: the truth resampled to R^3 and back")
    parser.add_argument("--blur", type=float, action="append", default=[],
                        help="also each run blurred by a Gaussian of this many cells")
    parser.add_argument("--mean", action="store_true",
                        help="also the runs' extinctions averaged cell by cell")
    parser.add_argument("--by", choices=list(BINS), default="extinction",
                        help="bin the cells by the true sigma_t or by the optical depth from "
                             "outside the box")
    parser.add_argument("--bins", default=None,
                        help=f"inner bin edges (default {BINS})")
    args = parser.parse_args()
    if not args.runs and args.scene is None:
        parser.error("give run folders, or --scene NAME (with --floor R) for the floors alone")
    dataset = args.dataset
    if args.scene is not None:
        truth, dataset = scene_truth(args.scene, args.preset), f"scene {args.scene}"
    else:
        if dataset is None:
            dataset = Path(json.loads((args.runs[0] / "run.json").read_text())["dataset_dir"])
        truth = truth_grids(dataset)
    # nrt writes the bbox with every ground truth; another tool's file gets the default box
    bbox = truth.pop("bbox", np.array([[-1.0] * 3, [1.0] * 3]))
    true_t = truth["sigma_a"] + truth["sigma_s"]
    resolution = true_t.shape[0]
    key = None
    if args.by == "depth":
        key = depth_from_outside(true_t.mean(-1), (bbox[1] - bbox[0]) / resolution)
    edges = [0.0, *(float(b) for b in (args.bins or BINS[args.by]).split(",")), float("inf")]
    bins = [f"[{lo:g}, {hi:g})" for lo, hi in itertools.pairwise(edges)]
    what = "the true sigma_t" if args.by == "extinction" else "the true optical depth from outside"
    print(f"dataset {dataset} ({resolution}^3); per bin of {what}: "
          "cells / error share / bias / rms")
    print("| medium | sigma_t MSE x100 | inflated share | " + " | ".join(bins) + " |")
    print("|---|---:|---:|" + "---:|" * len(bins))
    estimates = []
    for run in args.runs:
        estimate = run_extinction(run, resolution)
        estimates.append(estimate)
        print(f"| {run} | " + " | ".join(error_row(estimate, true_t, edges, key)) + " |")
        for sigma in args.blur:
            print(f"| {run}, blurred {sigma:g} cells | " + " | ".join(
                error_row(gaussian_blur(estimate, sigma), true_t, edges, key)) + " |")
    if args.mean:
        print(f"| mean of the {len(estimates)} runs | " + " | ".join(
            error_row(np.mean(estimates, axis=0), true_t, edges, key)) + " |")
    for r in args.floor:
        back = resample_grids(resample_grids(_tensors(truth), r), resolution)
        floor_t = np.asarray(back["sigma_a"] + back["sigma_s"], dtype=np.float64)
        print(f"| truth on {r}^3 (floor) | " + " | ".join(error_row(floor_t, true_t, edges, key))
              + " |")


if __name__ == "__main__":
    main()
