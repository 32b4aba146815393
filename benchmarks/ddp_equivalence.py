"""One process against two at the same total rays per step, at ``tiny`` on ``default``.

``trainer=cpu`` with the preset's counts against ``trainer=ddp_cpu`` (2 gloo processes) with
every per-step count halved (budgets are per rank, docs/cli.md "Several processes"), for
each seed: stage 1 (the held-out PSNR and the density correlation at its end) and stage 2
from one fixed EA checkpoint (the property MSEs and the held-out PSNR at its end). The two
processes' runs match the one's when the difference of the means lies within the seeds'
spread; the summary prints both.

    python -m benchmarks.ddp_equivalence [--seeds 0,1,2] [--stages ea,rte]
        [--csv docs/data/ddp_equivalence.csv]
    python -m benchmarks.ddp_equivalence --summary   # from the CSV alone

Runs of other seeds or stages already in the CSV are kept (``--seeds 3,4,5`` adds seeds).

Runs one after another (never two trainings at once); each run's folder lands under
``<output>/benchmarks/ddp_equivalence``.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from pathlib import Path

from omegaconf import OmegaConf

from benchmarks.common import compose_train, ea_checkpoint, metric_rows, output_dir, train

HALVED = {
    "ea": ("budget.ea.rays_per_batch",),
    "rte": ("budget.rte.rays_per_batch", "budget.rte.photo_rays", "budget.rte.vre_rays",
            "budget.rte.transport_points"),
}
"""The counts a step draws, per stage, that a rank of two processes draws half of."""

METRICS = {
    "ea": ("val/psnr", "val/density_corr"),
    "rte": ("val/mse_sigma_t_x100", "val/mse_sigma_s_x100", "val/mse_sigma_a_x100",
            "val/psnr"),
}
"""The end-of-run metrics compared, per stage."""


COUNTS = ("processes", "seed", "steps")
"""Columns of the CSV that hold whole numbers."""


def halved(stage: str) -> list[str]:
    """Overrides giving each of two ranks half of the ``tiny`` preset's per-step counts."""
    cfg = compose_train(["preset=tiny"])
    out = []
    for key in HALVED[stage]:
        value = OmegaConf.select(cfg, key)
        if value % 2:
            raise SystemExit(f"{key}={value} is odd: two ranks cannot draw half each.")
        out.append(f"{key}={value // 2}")
    return out


def last(rows: list[dict], key: str) -> float:
    values = [float(r[key]) for r in rows if r.get(key)]
    if not values:
        raise SystemExit(f"no {key} in the run's metrics")
    return values[-1]


def run(stage: str, processes: int, seed: int, out: Path, start: list[str]) -> dict:
    trainer = "cpu" if processes == 1 else "ddp_cpu"
    overrides = [f"trainer={trainer}", f"seed={seed}", *start,
                 *(halved(stage) if processes == 2 else [])]
    folder, wall = train(stage, out, "tiny", overrides, logger="csv")
    rows = metric_rows(folder)
    steps = max(int(float(r["step"])) for r in rows if r.get("step"))
    return {"stage": stage, "processes": processes, "seed": seed, "steps": steps,
            "wall_s": round(wall, 1), **{key: last(rows, key) for key in METRICS[stage]}}


def read_rows(path: Path) -> list[dict]:
    """The runs recorded in the CSV (none when it does not exist), numbers as floats."""
    if not path.is_file():
        return []
    with open(path) as f:
        return [{k: v if k == "stage" else int(v) if k in COUNTS else float(v)
                 for k, v in r.items() if v != ""} for r in csv.DictReader(f)]


def summary(rows: list[dict]) -> list[str]:
    """A line per stage and metric: the mean and seed spread (sample sd) of each process
    count, their difference, whether it lies within the larger spread, and Welch's t."""
    lines = []
    for stage in dict.fromkeys(r["stage"] for r in rows):
        for key in METRICS[stage]:
            by = {p: [r[key] for r in rows if r["stage"] == stage and r["processes"] == p]
                  for p in (1, 2)}
            if min(len(v) for v in by.values()) < 2:
                continue
            mean = {p: statistics.mean(v) for p, v in by.items()}
            sd = {p: statistics.stdev(v) for p, v in by.items()}
            diff = mean[2] - mean[1]
            verdict = "within" if abs(diff) <= max(sd.values()) else "outside"
            error = math.sqrt(sum(sd[p] ** 2 / len(by[p]) for p in by))
            welch = f"{diff / error:+.1f}" if error > 0 else "-"
            lines.append(f"{stage} {key}: 1 process {mean[1]:.4g} +- {sd[1]:.2g} "
                         f"({len(by[1])} seeds), 2 processes {mean[2]:.4g} +- {sd[2]:.2g} "
                         f"({len(by[2])}); difference {diff:+.3g}, {verdict} the seed spread "
                         f"(Welch t {welch})")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--stages", default="ea,rte")
    parser.add_argument("--csv", type=Path, default=Path("docs/data/ddp_equivalence.csv"))
    parser.add_argument("--summary", action="store_true",
                        help="print the summary of the CSV's runs; train nothing")
    args = parser.parse_args()
    if args.summary:
        print("\n".join(summary(read_rows(args.csv))))
        return
    seeds = [int(s) for s in args.seeds.split(",")]
    out = output_dir() / "benchmarks" / "ddp_equivalence"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for stage in args.stages.split(","):
        start = [] if stage == "ea" else [f"init.ea_ckpt={ea_checkpoint('default', 'tiny')}"]
        for seed in seeds:
            for processes in (1, 2):
                rows.append(run(stage, processes, seed, out, start))
                print(rows[-1], flush=True)
    done = {(r["stage"], r["processes"], r["seed"]) for r in rows}
    rows = [r for r in read_rows(args.csv) if (r["stage"], r["processes"], r["seed"])
            not in done] + rows  # runs of other seeds or stages recorded before are kept
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows(rows)
    print("\n".join(summary(rows)))


if __name__ == "__main__":
    main()
