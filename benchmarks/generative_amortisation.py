"""Amortisation, the generative mode's argument: the training seconds its two stages take
to bring a family's mean sigma_t MSE down to the mean that K single-scene runs reach, against
those K runs' total.

The reference: each member of the preset's family alone (``scene.path=<member folder>``,
the family's training sky only, as the generative run sees it), single-scene stage 1 and
stage 2 at the preset's defaults, one seed. The generative mode: generative stage 1 and
stage 2 at their defaults (:mod:`benchmarks.generative_stage2`'s ``default``), or the
stage-1 and stage-2 configurations ``--stage1`` and ``--config`` name, the same seed.
Finished runs that train the same config are reused (:func:`benchmarks.common.run_like`),
the others trained one at a time. Rows go to ``--table`` (CSV): ``single``, one per member
(its stage-1 and stage-2 training seconds, its sigma_t MSE x100 at stage 2's start and end),
and ``generative``, one per validation of the generative stage-2 run (stage 1's seconds,
stage 2's seconds so far, the members' mean sigma_t there, its ``stage1`` and ``config``).
Rows that exist (the single runs of a preset and seed, a generative run of a preset, seed,
stage1 and config) are not measured again. ``--summary`` prints the comparison, a line per
generative run, from the table alone.

    python -m benchmarks.generative_amortisation [--preset cpu] [--seed 0]
        [--stage1 default] [--config default]
        [--table docs/data/generative_amortisation.csv] [--summary]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks import generative_stage1, generative_stage2
from benchmarks.common import append_rows, read_table, run_like, validation_rows
from nrt.run_dirs import LAST_CKPT, read_run_info

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_amortisation.csv"
FIELDS = ("kind", "preset", "seed", "member", "step", "stage1_s", "stage2_s",
          "sigma_t_start", "sigma_t", "stage1", "config")
SIGMA_T = "val/mse_sigma_t_x100"  # a generative run's: the mean over its members


def wall_s(run: Path) -> float:
    """A finished run's training seconds."""
    return float(read_run_info(run)["final_metrics"]["time/wall_s"])


def single_rows(preset: str, seed: int) -> list[dict]:
    """One row per member: single-scene stage 1, then stage 2 from it."""
    rows = []
    for k, overrides in enumerate(generative_stage1.member_overrides(preset, seed)):
        ea = run_like("ea", preset, overrides, logger="[csv]")
        rte = run_like("rte", preset, [*overrides, f"init.ea_ckpt={(ea / LAST_CKPT).resolve()}"])
        curve = validation_rows(rte)
        rows.append({"kind": "single", "preset": preset, "seed": seed, "member": k,
                     "step": int(curve[-1]["step"]), "stage1_s": f"{wall_s(ea):.1f}",
                     "stage2_s": f"{wall_s(rte):.1f}",
                     "sigma_t_start": f"{curve[0][SIGMA_T]:.4f}",
                     "sigma_t": f"{curve[-1][SIGMA_T]:.4f}"})
    return rows


def generative_rows(preset: str, seed: int, stage1: str = "default",
                    config: str = "default") -> list[dict]:
    """One row per validation of the generative stage-2 run of configuration ``config`` (a
    name of :data:`benchmarks.generative_stage2.CONFIGS`) from the generative stage 1 of
    ``stage1``, with the seconds of both stages so far."""
    ckpt = generative_stage2.stage1_checkpoint(stage1, preset, seed)
    rte = run_like("rte", preset, ["scene=family", "mode=generative", f"init.ea_ckpt={ckpt}",
                                   *generative_stage2.CONFIGS[config], f"seed={seed}"])
    stage1_s = wall_s(ckpt.parent.parent)
    curve = validation_rows(rte)
    return [{"kind": "generative", "preset": preset, "seed": seed, "member": "",
             "step": int(r["step"]), "stage1_s": f"{stage1_s:.1f}",
             "stage2_s": f"{r['time/wall_s']:.1f}",
             "sigma_t_start": f"{curve[0][SIGMA_T]:.4f}", "sigma_t": f"{r[SIGMA_T]:.4f}",
             "stage1": stage1, "config": config}
            for r in curve]


def run_name(row: dict) -> str:
    """A generative row's run: its stage-1 and stage-2 configurations (``default`` in a
    table written before they were recorded)."""
    return f"{row.get('stage1') or 'default'} / {row.get('config') or 'default'}"


def summary(rows: list[dict]) -> str:
    """Per (preset, seed) and generative run: the K single-scene runs' mean sigma_t start ->
    end and their total seconds; the seconds (both stages) at which the generative run's
    mean first reaches that end, or its best mean where it never does; and the ratio of the
    two times."""
    lines = ["| preset | seed | generative run (stage 1 / stage 2) "
             "| K single runs: sigma_t start -> end | their seconds "
             "| generative: start -> end | seconds to reach the single runs' end "
             "| generative / single time |", "|---|---:|---|---:|---:|---:|---:|---:|"]
    groups: dict[tuple[str, str], dict[str, list[dict]]] = {}
    for row in rows:
        kind = "single" if row["kind"] == "single" else run_name(row)
        groups.setdefault((row["preset"], str(row["seed"])), {}).setdefault(
            kind, []).append(row)
    for (preset, seed), kinds in groups.items():
        single = kinds.pop("single", [])
        if not single:
            continue
        target = statistics.fmean(float(r["sigma_t"]) for r in single)
        single_s = sum(float(r["stage1_s"]) + float(r["stage2_s"]) for r in single)
        start = statistics.fmean(float(r["sigma_t_start"]) for r in single)
        for name, generative in kinds.items():
            curve = sorted(generative, key=lambda r: int(r["step"]))
            reached = next((r for r in curve if float(r["sigma_t"]) <= target), None)
            if reached is not None:
                seconds = float(reached["stage1_s"]) + float(reached["stage2_s"])
                when, ratio = f"{seconds:.0f}", f"{seconds / single_s:.2f}"
            else:
                best = min(curve, key=lambda r: float(r["sigma_t"]))
                when = (f"not reached (best {float(best['sigma_t']):.1f} at "
                        f"{float(best['stage1_s']) + float(best['stage2_s']):.0f} s)")
                ratio = "-"
            lines.append(f"| {preset} | {seed} | {name} | {start:.1f} -> {target:.1f} | "
                         f"{single_s:.0f} | {float(curve[0]['sigma_t']):.1f} -> "
                         f"{float(curve[-1]['sigma_t']):.1f} | {when} | {ratio} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stage1", default="default", choices=sorted(generative_stage1.CONFIGS),
                        help="the generative stage 1's configuration")
    parser.add_argument("--config", default="default", choices=sorted(generative_stage2.CONFIGS),
                        help="the generative stage 2's configuration")
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if not args.summary:
        rows = read_table(args.table)
        here = [r for r in rows if (r["preset"], r["seed"]) == (args.preset, str(args.seed))]
        name = run_name({"stage1": args.stage1, "config": args.config})
        if not any(r["kind"] == "generative" and run_name(r) == name for r in here):
            append_rows(args.table, FIELDS,
                        generative_rows(args.preset, args.seed, args.stage1, args.config))
        if not any(r["kind"] == "single" for r in here):
            append_rows(args.table, FIELDS, single_rows(args.preset, args.seed))
    print(summary(read_table(args.table)))


if __name__ == "__main__":
    main()
