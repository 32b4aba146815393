"""Single-scene stage 2 started from the true extinction on members of a family: whether
stage 2 keeps a sharp medium sharp, and what the extinction prior does to dense cores.

A generative run's reconstructions hold an extinction blurred about 2.5 cells wide
(``benchmarks.generative_recon_gap``). This benchmark asks whether the photos pull a sharp
medium toward that blur. For each member of ``--members`` (of the preset's family, rendered
first where missing) and each extinction-prior weight of ``--priors``: single-scene
``nrt-train stage=rte init=oracle`` (stage 2 modulating the member's true extinction), on the
family's training sky alone as the generative run sees it, seed ``--seed``, through the CLI
(a finished run that trains the same is reused: ``benchmarks.common.run_like``). A row per
run in ``--table``:

- sigma_t MSE x100 at its first and last validation, held-out PSNR, training seconds;
- the least sigma_t MSE x100 against the truth blurred by s cells of the truth's grid, and
  that s (``benchmarks.generative_recon_gap``'s blurs): the scale of the blur it holds;
- its extinction over the truth's in the thin cells (true sigma_t < 0.5, channel mean) and
  the dense ones (>= 2), and its mean signed sigma_t error in the dense cells;
- the same for the floor (the truth on the run's cells, ``budget.rte.density_resolution``^3,
  and back): what those cells alone cost.

``--summary`` prints the table; rows already there are skipped.

    python -m benchmarks.generative_oracle [--preset cpu] [--members 0,1] [--priors 1e-4,0]
        [--seed 1] [--table docs/data/generative_oracle.csv] [--summary]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from benchmarks.common import (
    append_rows,
    compose_train,
    read_table,
    run_finals,
    run_like,
    validation_rows,
)
from benchmarks.generative_recon_gap import BANDS, band_rows, blur_rows, extinction

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_oracle.csv"
FIELDS = ("preset", "member", "prior", "seed", "sigma_t_start", "sigma_t_end", "psnr",
          "train_s", "least_blur_mse", "least_blur_cells", "thin_ratio", "dense_ratio",
          "dense_bias", "floor_least_blur_cells", "floor_thin_ratio", "floor_dense_ratio",
          "floor_dense_bias", "run")


def medium_stats(truth: dict, medium: dict) -> dict[str, float]:
    """``medium``'s least sigma_t MSE x100 against the truth blurred by s cells and that s;
    its extinction over the truth's in the thin and dense bands; its mean signed sigma_t
    error in the dense cells (grids on the truth's cells: ``sigma_a``, ``sigma_s``, ...)."""
    blurs = blur_rows([truth], {"m": [medium]}, "", "")
    least = min(blurs, key=lambda r: float(r["mse_sigma_t_x100"]))
    ratios = {r["band"]: float(r["ratio_mean"] or "nan")  # nan: the truth has no such cells
              for r in band_rows([truth], {"m": [medium]}, "", "")}
    true = extinction(truth).double()
    dense = true.mean(-1) >= BANDS["dense"][0]
    bias = float((extinction(medium).double() - true)[dense].mean())
    return {"least_blur_mse": float(least["mse_sigma_t_x100"]),
            "least_blur_cells": float(least["blur_cells"]), "thin_ratio": ratios["thin"],
            "dense_ratio": ratios["dense"], "dense_bias": bias}


def as_tensors(grids: dict) -> dict[str, torch.Tensor]:
    """Property grids as float64 tensors (``bbox`` left out)."""
    return {k: torch.as_tensor(np.asarray(v, np.float64)) for k, v in grids.items()
            if k != "bbox"}


def run_row(run: Path, preset: str, member: int, prior: str, seed: int) -> dict:
    """The table's row of one finished oracle run (the module docstring's figures)."""
    from nrt.data.grids import load_property_grids, resample_grids
    from nrt.run_dirs import read_run_info

    dataset = Path(read_run_info(run)["dataset_dir"])
    truth = as_tensors(load_property_grids(dataset / "ground_truth.npz"))
    size = truth["sigma_a"].shape[0]
    cells = int(OmegaConf.load(run / ".hydra" / "config.yaml").budget.rte.density_resolution)
    medium = as_tensors(resample_grids(load_property_grids(run / "medium_grids.npz"), size))
    floor = as_tensors(resample_grids(resample_grids(truth, cells), size))
    checks = validation_rows(run)
    finals = run_finals(run, {"psnr": "val/psnr"})
    row = {"preset": preset, "member": member, "prior": prior, "seed": seed,
           "sigma_t_start": checks[0]["val/mse_sigma_t_x100"],
           "sigma_t_end": checks[-1]["val/mse_sigma_t_x100"], "psnr": finals.get("psnr", ""),
           "train_s": finals["train_s"], **medium_stats(truth, medium),
           **{f"floor_{k}": v for k, v in medium_stats(truth, floor).items()
              if k != "least_blur_mse"}, "run": str(run)}
    return {k: f"{v:.4f}" if isinstance(v, float) else v for k, v in row.items()}


def measure(preset: str, members: list[int], priors: list[str], seed: int,
            table: Path) -> None:
    """Train (or find) and record every (member, prior) not yet in ``table``; members
    outside the preset's family are refused from its config, before the family renders."""
    from benchmarks.generative_stage1 import member_overrides

    count = int(compose_train(["scene=family", f"preset={preset}"]).scene.family.members)
    if max(members) >= count:
        sys.stderr.write(f"generative_oracle: error: --members {max(members)}: the {preset} "
                         f"family has members 0..{count - 1}; give positions among them.\n")
        sys.exit(2)
    done = {(r["preset"], r["member"], r["prior"], r["seed"]) for r in read_table(table)}
    todo = [(m, p) for m in members for p in priors
            if (preset, str(m), p, str(seed)) not in done]
    if not todo:
        return
    overrides = member_overrides(preset, seed)
    for member, prior in todo:
        run = run_like("rte", preset, [*overrides[member], "init=oracle",
                                       f"losses.weights.extinction_prior={prior}"],
                       logger="[csv]")
        append_rows(table, FIELDS, [run_row(run, preset, member, prior, seed)])
        print(summary(read_table(table)), flush=True)


def summary(rows: list[dict]) -> str:
    """The table as markdown: per run its start and end, PSNR, the blur it holds and its
    bands, the floor's beside them."""
    lines = ["| preset | member | prior | seed | sigma_t start -> end | PSNR | least error "
             "against the blurred truth (at s cells; floor's s) | thin cells x truth (floor) "
             "| dense cells x truth (floor) | dense bias (floor) | training s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        f = {k: float(v) for k, v in r.items() if k not in ("preset", "prior", "run", "psnr")}
        psnr = f"{float(r['psnr']):.2f}" if r["psnr"] else ""
        lines.append(
            f"| {r['preset']} | {r['member']} | {r['prior']} | {r['seed']} | "
            f"{f['sigma_t_start']:.2f} -> {f['sigma_t_end']:.2f} | {psnr} | "
            f"{f['least_blur_mse']:.2f} ({f['least_blur_cells']:.1f}; "
            f"{f['floor_least_blur_cells']:.1f}) | {f['thin_ratio']:.1f} "
            f"({f['floor_thin_ratio']:.1f}) | {f['dense_ratio']:.3f} "
            f"({f['floor_dense_ratio']:.3f}) | {f['dense_bias']:+.3f} "
            f"({f['floor_dense_bias']:+.3f}) | {f['train_s']:.0f} |")
    return "\n".join(lines)


def whole_list(parser: argparse.ArgumentParser, key: str, text: str) -> list[int]:
    """``text`` as comma-separated whole numbers >= 0, else a usage error naming ``key``."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = [-1]
    if not values or any(v < 0 for v in values):
        parser.error(f"{key}={text!r}: give member positions, whole numbers >= 0 separated "
                     "by commas (e.g. 0,1).")
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--members", default="0,1")
    parser.add_argument("--priors", default="1e-4,0",
                        help="extinction-prior weights (losses.weights.extinction_prior)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--summary", action="store_true")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    members = whole_list(parser, "--members", args.members)
    priors = [p.strip() for p in args.priors.split(",")]
    for prior in priors:
        try:
            ok = float(prior) >= 0 and np.isfinite(float(prior))
        except ValueError:
            ok = False
        if not ok:
            parser.error(f"--priors: {prior!r} is no weight; give numbers >= 0 separated by "
                         "commas (e.g. 1e-4,0).")
    measure(args.preset, members, priors, args.seed, args.table)


if __name__ == "__main__":
    main()
