"""Where a generative run's reconstructions lose FID against the true media: each part of
the members' reconstructions replaced by the truth's, one at a time, rendered and scored as
the samples are; and how blurred the reconstructions' extinction is.

A generative run's samples can score no closer to the real photos than the members' own
reconstructions do (``benchmarks.generative_sampling``: a bootstrap at a small bandwidth
reaches the reconstructions' FID and no sampler goes below it). This benchmark holds one
finished generative stage-2 run (``--from-run``, folded as ``nrt-sample`` folds it) and
scores, under both skies and over ``--seeds`` (the FID's crops), the media sets of
:data:`SETS`: the true media, the true media on the run's cells (``floor``), the
reconstructions, and the reconstructions with one part taken from the truth:

- ``recon_albedo_from_truth``, ``recon_g_from_truth``, ``recon_albedo_g_from_truth``: the
  reconstruction's extinction (per channel) with the truth's albedo (``sigma_s / sigma_t``
  per cell and channel, the reconstruction's where the truth is empty) and/or g;
  ``truth_albedo_g_from_recon``: the converse, the truth's extinction with the
  reconstruction's albedo and g;
- ``recon_<band>_from_floor``: the reconstruction with the cells whose true extinction
  (channel mean) lies in a band replaced by the floor's (``sigma_a``, ``sigma_s``; g stays
  the reconstruction's): :data:`BANDS`, empty (< 1e-3), thin (< 0.5, empty included),
  mid [0.5, 2) and dense (>= 2), the bins of ``benchmarks.medium_error``.

A set whose FID falls toward the truth's locates a share of the reconstructions' gap.
Every set has 16 media rendered as ``reference_renders`` renders (render seed 1 + n + k for
member k). A row per (run, set, seed) in ``--table``; rows already there are skipped.

Beside FID: the reconstructions', the floor's and the stage-1 densities' the run started
from (``stage1``) sigma_t MSE x100 (members' mean) against the truth blurred by a Gaussian
of s cells of the truth's grid (``benchmarks.medium_error.gaussian_blur``, s = 0 the truth
itself), for s in :data:`BLURS`: the s where a medium's error is least is the scale of the
blur it holds (the floor's, about one cell, is what the run's cells cost). Rows in
``--blur-table``; and in ``--band-table``, per medium and band of :data:`BANDS`, the share
of each member's extinction that lies there and its ratio to the truth's there (``--seeds
''``: these rows alone, in seconds).

    python -m benchmarks.generative_recon_gap --from-run DIR [--label NAME] [--seeds 0,1,2]
        [--table docs/data/generative_recon_gap.csv]
        [--blur-table docs/data/generative_recon_blur.csv]
        [--band-table docs/data/generative_recon_bands.csv] [--summary]
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import append_rows, read_table
from benchmarks.generative_sampling import COLUMNS, add_run_arguments, checked_run, spread

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_recon_gap.csv"
BLUR_TABLE = ROOT / "docs" / "data" / "generative_recon_blur.csv"
BAND_TABLE = ROOT / "docs" / "data" / "generative_recon_bands.csv"
BANDS = {"empty": (0.0, 1e-3), "thin": (0.0, 0.5), "mid": (0.5, 2.0), "dense": (2.0, np.inf)}
"""Bands of the true extinction (channel mean, per unit length) a set takes from the floor."""
SETS = ("truth", "floor", "recon", "recon_albedo_from_truth", "recon_g_from_truth",
        "recon_albedo_g_from_truth", "truth_albedo_g_from_recon",
        *(f"recon_{band}_from_floor" for band in BANDS))
"""The media sets scored, in the table's order."""
BLURS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5)
"""Gaussian standard deviations (cells of the truth's grid) the truth is blurred by."""
FIELDS = ("label", "run", "set", "seed", "n", "fid_train", "fid_novel")
BLUR_FIELDS = ("label", "run", "medium", "blur_cells", "mse_sigma_t_x100")
BAND_FIELDS = ("label", "run", "medium", "band", "share_mean", "share_min", "share_max",
               "ratio_mean", "ratio_min", "ratio_max")
EMPTY = 1e-4
"""Extinction below which a medium's cell counts as empty when its albedo is taken."""


def extinction(grids: dict) -> torch.Tensor:
    """sigma_t per cell and channel."""
    return grids["sigma_a"] + grids["sigma_s"]


def albedo(grids: dict, fallback: dict) -> torch.Tensor:
    """``grids``' albedo per cell and channel; ``fallback``'s where ``grids`` is empty."""
    sigma_t, other = extinction(grids), extinction(fallback)
    own = grids["sigma_s"] / sigma_t.clamp_min(1e-6)
    return torch.where(sigma_t > EMPTY, own, fallback["sigma_s"] / other.clamp_min(1e-6))


def with_albedo_g(density: dict, albedo_of: dict, g_of: dict) -> dict:
    """``density``'s extinction with ``albedo_of``'s albedo (``density``'s where
    ``albedo_of`` is empty) and ``g_of``'s g."""
    sigma_t, a = extinction(density), albedo(albedo_of, density)
    return {"sigma_a": (1 - a) * sigma_t, "sigma_s": a * sigma_t, "g": g_of["g"]}


def band_from(recon: dict, floor: dict, truth: dict, band: tuple[float, float]) -> dict:
    """``recon`` with the cells whose true extinction (channel mean) lies in ``band``
    [lo, hi) taken from ``floor`` (``sigma_a``, ``sigma_s``; g stays ``recon``'s)."""
    mean = extinction(truth).mean(-1)
    inside = ((mean >= band[0]) & (mean < band[1]))[..., None]
    return {"sigma_a": torch.where(inside, floor["sigma_a"], recon["sigma_a"]),
            "sigma_s": torch.where(inside, floor["sigma_s"], recon["sigma_s"]),
            "g": recon["g"]}


def media_sets(truths: list[dict], floor: list[dict], recon: list[dict]) -> dict[str, list]:
    """Every set of :data:`SETS` by name, a medium per member."""
    members = list(zip(truths, floor, recon, strict=True))
    sets = {"truth": truths, "floor": floor, "recon": recon,
            "recon_albedo_from_truth": [with_albedo_g(r, t, r) for t, _, r in members],
            "recon_g_from_truth": [with_albedo_g(r, r, t) for t, _, r in members],
            "recon_albedo_g_from_truth": [with_albedo_g(r, t, t) for t, _, r in members],
            "truth_albedo_g_from_recon": [with_albedo_g(t, r, r) for t, _, r in members]}
    for name, band in BANDS.items():
        sets[f"recon_{name}_from_floor"] = [band_from(r, f, t, band) for t, f, r in members]
    return sets


def blur_rows(truths: list[dict], media: dict[str, list[dict]], label: str,
              run: str) -> list[dict]:
    """Per medium set of ``media`` and blur of :data:`BLURS`: the members' mean sigma_t
    MSE x100 against the truth blurred by that many cells."""
    from benchmarks.medium_error import gaussian_blur

    def blurred(t: dict, s: float) -> np.ndarray:
        grid = extinction(t).double().numpy()
        return grid if s == 0 else gaussian_blur(grid, s)

    rows = []
    for s in BLURS:
        targets = [blurred(t, s) for t in truths]
        for name, grids in media.items():
            mse = statistics.fmean(
                float(100 * ((extinction(m).double().numpy() - b) ** 2).mean())
                for m, b in zip(grids, targets, strict=True))
            rows.append({"label": label, "run": run, "medium": name, "blur_cells": s,
                         "mse_sigma_t_x100": f"{mse:.4f}"})
    return rows


def stage1_media(run: Path, names: list[str], resolution: int) -> list[dict]:
    """The generative stage-1 densities the stage-2 ``run`` started from (its
    ``init.ea_ckpt``'s run, ``members/<name>/density_grid.npz``) on ``resolution``^3 cells,
    as sigma_t in every channel (``benchmarks.medium_error.run_extinction``)."""
    from benchmarks.medium_error import run_extinction
    from nrt.evaluation.runs import read_run_folder

    stage1 = Path(read_run_folder(run)[2].init.ea_ckpt).parent.parent
    media = []
    for name in names:
        sigma_t = torch.from_numpy(run_extinction(stage1 / "members" / name, resolution))
        media.append({"sigma_a": sigma_t, "sigma_s": torch.zeros_like(sigma_t)})
    return media


def band_rows(truths: list[dict], media: dict[str, list[dict]], label: str,
              run: str) -> list[dict]:
    """Per medium set of ``media`` and band of :data:`BANDS`: the share of each member's
    extinction (summed over cells and channels) that lies in the band's cells, and its
    ratio to the truth's extinction there (over the members whose truth is not empty there:
    a mean extinction of at least the empty band's edge); mean, least and most over the
    members, empty where there is none."""
    rows = []
    for name, grids in media.items():
        for band, (lo, hi) in BANDS.items():
            shares, ratios = [], []
            for m, t in zip(grids, truths, strict=True):
                mean = extinction(t).double().mean(-1)
                inside = (mean >= lo) & (mean < hi)
                own = extinction(m).double()
                shares.append(float(own[inside].sum() / own.sum()))
                true = extinction(t).double()[inside]
                if true.numel() and float(true.mean()) >= BANDS["empty"][1]:
                    ratios.append(float(own[inside].sum() / true.sum()))
            row = {"label": label, "run": run, "medium": name, "band": band}
            for key, values in (("share", shares), ("ratio", ratios)):
                row |= {f"{key}_{stat}": f"{f(values):.4f}" if values else ""
                        for stat, f in (("mean", statistics.fmean), ("min", min), ("max", max))}
            rows.append(row)
    return rows


def measure(run: Path, label: str, seeds: list[int], table: Path, blur_table: Path,
            band_table: Path) -> None:
    """The rows of ``run`` for every (set, seed) not yet in ``table``, and its blur and
    band rows when ``blur_table`` has none."""
    from benchmarks.generative_sampling import load_run

    done = {(r["run"], r["set"], r["seed"]) for r in read_table(table)}
    todo = [s for s in seeds if any((str(run), name, str(s)) not in done for name in SETS)]
    blurred = any(r["run"] == str(run) for r in read_table(blur_table))
    if not todo and blurred:
        return
    loaded = load_run(run, 16)
    truths = loaded.data.truths
    sets = media_sets(truths, loaded.floor, loaded.recon_media)
    if not blurred:
        media = {"recon": loaded.recon_media, "floor": loaded.floor,
                 "stage1": stage1_media(run, loaded.model.member_names(), loaded.resolution)}
        append_rows(blur_table, BLUR_FIELDS, blur_rows(truths, media, label, str(run)))
        append_rows(band_table, BAND_FIELDS, band_rows(truths, media, label, str(run)))
    if not todo:
        return
    references = {name: loaded.renders(media) for name, media in sets.items()}
    for seed in todo:
        scorer = loaded.scorer(seed, references)
        append_rows(table, FIELDS, [
            {"label": label, "run": str(run), "set": name, "seed": seed, "n": loaded.base.n,
             **{f"fid_{col}": f"{scorer.references[name][col]:.3f}" for col in COLUMNS}}
            for name in SETS if (str(run), name, str(seed)) not in done])
        print(summary(read_table(table), read_table(blur_table), read_table(band_table)),
              flush=True)


def summary(rows: list[dict], blur: list[dict], bands: Sequence[dict] = ()) -> str:
    """Per (label, set): FID under both skies, mean ± sd over seeds, and its change from
    the reconstructions' (seed by seed: both scored on the same crops), mean ± sd; then per
    (label, medium) the blur whose MSE is least; then per (label, medium, band) its share
    of the extinction and its ratio to the truth's, mean (least-most) over members."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["label"], r["set"]), []).append(r)

    def change(label: str, group: list[dict], col: str) -> str:
        recon = {r["seed"]: float(r[f"fid_{col}"]) for r in groups.get((label, "recon"), [])}
        paired = [float(r[f"fid_{col}"]) - recon[r["seed"]] for r in group
                  if r["seed"] in recon]
        if not paired:
            return ""
        return f"{'+' if statistics.fmean(paired) >= 0 else ''}{spread(paired)}"

    lines = ["| run | media | seeds | FID train | novel | vs recon: train | novel |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for (label, name), group in groups.items():
        lines.append(f"| {label} | {name} | {len(group)} | "
                     + " | ".join(spread([float(r[f"fid_{col}"]) for r in group])
                                  for col in COLUMNS) + " | "
                     + " | ".join(change(label, group, col) for col in COLUMNS) + " |")
    by_medium: dict[tuple[str, str], list[dict]] = {}
    for r in blur:
        by_medium.setdefault((r["label"], r["medium"]), []).append(r)
    if by_medium:
        lines += ["", "| run | medium | sigma_t MSE x100 to the truth | least, at blur (cells) |",
                  "|---|---|---:|---:|"]
        for (label, medium), group in by_medium.items():
            own = next(float(r["mse_sigma_t_x100"]) for r in group
                       if float(r["blur_cells"]) == 0)
            best = min(group, key=lambda r: float(r["mse_sigma_t_x100"]))
            lines.append(f"| {label} | {medium} | {own:.2f} | "
                         f"{float(best['mse_sigma_t_x100']):.2f} at "
                         f"{float(best['blur_cells']):.1f} |")
    if bands:
        lines += ["", "| run | medium | band | share of its extinction | to the truth's there |",
                  "|---|---|---|---:|---:|"]
        for r in bands:
            lines.append(f"| {r['label']} | {r['medium']} | {r['band']} | " + " | ".join(
                f"{float(r[k + '_mean']):.3f} ({float(r[k + '_min']):.3f}-"
                f"{float(r[k + '_max']):.3f})" if r[k + "_mean"] else ""
                for k in ("share", "ratio")) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--seeds", default="0,1,2",
                        help="the FID's seeds; empty (--seeds '') for the blur and band rows alone")
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--blur-table", type=Path, default=BLUR_TABLE)
    parser.add_argument("--band-table", type=Path, default=BAND_TABLE)
    parser.add_argument("--summary", action="store_true", help="print the tables and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table), read_table(args.blur_table),
                      read_table(args.band_table)))
        return
    run, label = checked_run(parser, args)
    measure(run, label, [int(s) for s in args.seeds.split(",") if s], args.table,
            args.blur_table, args.band_table)


if __name__ == "__main__":
    main()
