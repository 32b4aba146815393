"""Generative stage 1's fit of every member of a family, its levers side by side.

For each configuration (a name and its overrides, :data:`CONFIGS`) and seed,
``nrt-train stage=ea mode=generative scene=family`` at the preset, through the CLI; each
member's density correlation with its truth at the last validation
(``val/density_corr_member<k>``), their mean and minimum, the held-out PSNR and the training
seconds go to ``--table`` (CSV), one row per run. The reference, configuration
``single``: single-scene stage 1 on each member's own photos (``scene.path=<member folder>``,
the family's training sky only, as the generative run sees them), one run per member, the
members' correlations in the same row (PSNR: their mean; seconds: their sum). A run whose
(config, preset, seed) row exists is skipped, and a finished run that trains the same config
is recorded instead of trained again, so a killed benchmark continues;
``--summary`` prints the mean and spread per configuration from the table alone.

    python -m benchmarks.generative_stage1 [--preset tiny] [--seeds 0,1,2]
        [--configs default,modulation_only,latent_input,latent_input_wide,
                   latent_input_f4,latent_dim16,single]
        [--table docs/data/generative_stage1.csv]
        [--summary]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks.common import (
    append_rows,
    compose_train,
    metric_rows,
    output_dir,
    read_table,
    run_like,
)
from nrt.data.family import ensure_family, load_family

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_stage1.csv"
CONFIGS = {
    "default": [],  # the latent input, twice the steps (mode.latent.ea_steps_scale=2)
    "modulation_only": ["mode.latent.input=false", "mode.latent.ea_steps_scale=1"],  # 1 + M(z)
    "latent_input": ["mode.latent.input=true", "mode.latent.ea_steps_scale=1"],  # z beside
    # with z as input, more capacity for the members to differ: a wider density MLP, or
    # twice the hash features a level (more spatial functions to combine per member)
    "latent_input_wide": ["mode.latent.input=true", "mode.latent.ea_steps_scale=1",
                          "model.density_field.hidden=128"],
    "latent_input_f4": ["mode.latent.input=true", "mode.latent.ea_steps_scale=1",
                        "model.density_field.hash_grid.features=4"],
    # sixteen code dimensions (d_z = 16) instead of the paper's four: room for each of 16
    # members' stage-2 corrections to differ (the decoders read z; the code bounds how far)
    "latent_dim16": ["mode.latent.dim=16"],
    # and four times the preset's steps: stage 1's densities are blurred about 3 cells wide
    # (docs/generative.md, "Where the reconstructions' gap sits") and twice the steps added
    # 0.04 of density correlation over one
    "latent_dim16_long": ["mode.latent.dim=16", "mode.latent.ea_steps_scale=4"],
    "single": [],  # the reference: single-scene stage 1 on each member (single_row)
}
"""The configurations measured, by name: their overrides of the generative defaults."""
FIELDS = ("config", "preset", "seed", "corr_mean", "corr_min", "corr_members", "psnr",
          "train_s", "overrides")


def last_values(run: Path) -> dict[str, float]:
    """Every metric's last logged value in a run's CSV log."""
    last: dict[str, float] = {}
    for row in metric_rows(run):
        last.update({k: float(v) for k, v in row.items() if v not in ("", None)})
    return last


def run_row(run: Path, config: str, preset: str, seed: int) -> dict:
    """The table's row of a finished generative stage-1 run."""
    last = last_values(run)
    members = [last[k] for k in sorted((k for k in last
                                         if k.startswith("val/density_corr_member")),
                                        key=lambda k: int(k.rsplit("member", 1)[1]))]
    return {"config": config, "preset": preset, "seed": seed,
            "corr_mean": f"{statistics.fmean(members):.4f}", "corr_min": f"{min(members):.4f}",
            "corr_members": ";".join(f"{c:.4f}" for c in members),
            "psnr": f"{last['val/psnr']:.3f}", "train_s": f"{last['time/wall_s']:.1f}",
            "overrides": " ".join(CONFIGS[config])}


def single_row(runs: list[Path], preset: str, seed: int) -> dict:
    """The table's row of the reference: one single-scene stage-1 run per member, in member
    order; the PSNR is their mean, the seconds their sum."""
    lasts = [last_values(run) for run in runs]
    members = [last["val/density_corr"] for last in lasts]
    return {"config": "single", "preset": preset, "seed": seed,
            "corr_mean": f"{statistics.fmean(members):.4f}", "corr_min": f"{min(members):.4f}",
            "corr_members": ";".join(f"{c:.4f}" for c in members),
            "psnr": f"{statistics.fmean(last['val/psnr'] for last in lasts):.3f}",
            "train_s": f"{sum(last['time/wall_s'] for last in lasts):.1f}", "overrides": ""}


def member_overrides(preset: str, seed: int) -> list[list[str]]:
    """Per member of the preset's family (rendered first where missing), in member order:
    the overrides that train that member alone, on the family's training sky only
    (environment 0 of every member), as the generative run sees it."""
    cfg = compose_train(["scene=family", f"preset={preset}"])
    family = load_family(ensure_family(cfg.scene, output_dir() / "datasets", progress=False))
    return [[f"scene.path={member.folder}", f"scene.name={member.name}",
             "stage.environments=[0]", f"seed={seed}"] for member in family.members]


def train_single(preset: str, seed: int) -> dict:
    """Single-scene stage 1 on each member of the preset's family (finished runs of the
    same config reused); the reference row."""
    return single_row([run_like("ea", preset, overrides, logger="[csv]")
                       for overrides in member_overrides(preset, seed)], preset, seed)


def summary(rows: list[dict]) -> str:
    """Mean (sd) over seeds per configuration and preset: the members' mean correlation, the
    worst member's, the held-out PSNR."""
    lines = ["| config | preset | seeds | density corr, mean of members | worst member | "
             "PSNR (dB) |", "|---|---|---:|---:|---:|---:|"]
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["config"], row["preset"]), []).append(row)

    def spread(values: list[float]) -> str:
        sd = statistics.stdev(values) if len(values) > 1 else 0.0
        return f"{statistics.fmean(values):.3f} ± {sd:.3f}"

    for (config, preset), group in groups.items():
        lines.append(f"| {config} | {preset} | {len(group)} | "
                     f"{spread([float(r['corr_mean']) for r in group])} | "
                     f"{min(float(r['corr_min']) for r in group):.3f} | "
                     f"{spread([float(r['psnr']) for r in group])} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    unknown = [c for c in args.configs.split(",") if c not in CONFIGS]
    if unknown:
        parser.error(f"--configs: unknown configuration {unknown[0]!r}; the known ones are "
                     f"{', '.join(CONFIGS)} (benchmarks/generative_stage1.py).")
    done = {(r["config"], r["preset"], r["seed"]) for r in read_table(args.table)}
    for seed in map(int, args.seeds.split(",")):
        for config in args.configs.split(","):
            if (config, args.preset, str(seed)) in done:
                continue
            if config == "single":
                row = train_single(args.preset, seed)
            else:
                run = run_like("ea", args.preset, ["scene=family", "mode=generative",
                                                   *CONFIGS[config], f"seed={seed}"],
                               logger="[csv]")
                row = run_row(run, config, args.preset, seed)
            append_rows(args.table, FIELDS, [row])
            print(f"{config} seed {seed}: density corr {row['corr_mean']} (worst "
                  f"{row['corr_min']}), {row['psnr']} dB, {row['train_s']} s", flush=True)


if __name__ == "__main__":
    main()
