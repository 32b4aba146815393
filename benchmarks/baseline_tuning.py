"""Tuning the path-tracing baseline (``stage=dpt``) and stage 2's levers (``--stage rte``) on
the tuning scenes, with a table kept.

Each configuration of a round (a list of Hydra overrides of the preset's defaults; the
baseline's rounds in ``benchmarks/baseline_tuning.yaml``, stage 2's in
``benchmarks/stage2_tuning.yaml``) trains the stage for ``--budget-s`` training seconds
from the scene's EA checkpoint (the newest under ``outputs/``, else a new stage-1 run),
with the property MSE measured every ``--every-s`` training seconds outside the clock. One
row per run is appended to the stage's table (``docs/data/baseline_tuning.csv`` or
``docs/data/stage2_tuning.csv``): the end's property MSE x100, the best sigma_t on the way
and when, steps and seconds. A stage-2 configuration may be a hybrid: stage 2 for part of
the budget, then the path-tracing baseline from stage 2's grids for the rest
(:func:`run_config`). A run whose (round, config, scene, preset, budget) row exists is
skipped, so a killed sweep resumes where it stopped.
Only the tuning scenes are accepted: nothing measured on a blind scene may choose a default.

    python -m benchmarks.baseline_tuning --round round1 [--stage dpt|rte] [--configs a,b]
        [--scenes default] [--budget-s 300] [--every-s 15] [--preset cpu] [--table CSV]
        [--out DIR]
    python -m benchmarks.baseline_tuning --summary [--stage dpt|rte] [--table CSV]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from benchmarks.common import (
    SCENES,
    TUNING_SCENES,
    add_budget_arguments,
    append_rows,
    ea_checkpoint,
    output_dir,
    read_table,
    series,
    train,
)

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {"dpt": Path(__file__).with_suffix(".yaml"),
           "rte": Path(__file__).with_name("stage2_tuning.yaml")}
TABLES = {"dpt": ROOT / "docs" / "data" / "baseline_tuning.csv",
          "rte": ROOT / "docs" / "data" / "stage2_tuning.csv"}
PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")
COLUMNS = ("round", "config", "stage", "scene", "preset", "budget_s", "seconds", "steps",
           *(f"mse_{k}_x100" for k in PROPERTIES), "start_sigma_t", "best_sigma_t",
           "best_at_s", "overrides")
MANY_STEPS = 1_000_000  # the budget stops the run


def run_row(run: Path) -> dict:
    """The measured columns of a finished run folder (its CSV log)."""
    wall = series(run, "time/wall_s")
    out = {"seconds": f"{wall[-1]:.1f}", "steps": int(max(series(run, "step"))) + 1}
    for key in PROPERTIES:
        values = series(run, f"val/mse_{key}_x100")
        out[f"mse_{key}_x100"] = f"{values[-1]:.4f}" if values else ""
    sigma_t = curve(run, "val/mse_sigma_t_x100")
    best = min(sigma_t, key=lambda p: p[1])
    out.update(start_sigma_t=f"{sigma_t[0][1]:.4f}", best_sigma_t=f"{best[1]:.4f}",
               best_at_s=f"{best[0]:.1f}")
    return out


def curve(run: Path, key: str) -> list[tuple[float, float]]:
    """(training seconds, value) of every logged value of ``key`` (rows that log it with
    ``time/wall_s`` beside)."""
    from benchmarks.common import metric_rows

    return [(float(r["time/wall_s"]), float(r[key])) for r in metric_rows(run)
            if r.get(key) and r.get("time/wall_s")]


def summary(rows: list[dict]) -> str:
    """Markdown: one line per (round, config, budget): the end's MSEs x100 averaged over the
    scenes it ran on, the best sigma_t on the way and when, the steps, and the overrides."""
    keyed: dict[tuple, list[dict]] = {}
    for r in rows:
        keyed.setdefault((r["round"], r["config"], r["stage"], r["budget_s"]), []).append(r)
    head = ["round", "config", "scenes", "budget s", "sigma_a", "sigma_s", "sigma_t", "g",
            "best sigma_t (at s)", "steps", "overrides"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|---|" + "---:|" * 7 + "---|"]

    def mean(runs: list[dict], key: str) -> float:
        values = [float(r[key]) for r in runs if r[key]]
        return sum(values) / len(values) if values else float("nan")

    for (rnd, config, stage, budget), runs in keyed.items():
        name = config if stage == "dpt" else f"{config} (stage=rte)"
        cells = [rnd, name, ", ".join(r["scene"] for r in runs), f"{float(budget):.0f}",
                 *(f"{mean(runs, f'mse_{k}_x100'):.3f}" for k in PROPERTIES),
                 f"{mean(runs, 'best_sigma_t'):.3f} ({mean(runs, 'best_at_s'):.0f})",
                 "/".join(str(r["steps"]) for r in runs), f"`{runs[0]['overrides']}`"
                 if runs[0]["overrides"] else "defaults"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def describe(config: list[str] | dict) -> str:
    """A configuration as the table's ``overrides`` column."""
    if isinstance(config, dict):
        return (f"{' '.join(config.get('overrides', []))} then stage=dpt for "
                f"{float(config['then_dpt']):.0%} of the time "
                f"{' '.join(config.get('dpt_overrides', []))}"
                ).strip()
    return " ".join(config)


def run_config(args, scene: str, ckpt: Path, budget: float,
               config: list[str] | dict) -> dict:
    """Train one configuration for ``budget`` training seconds from the EA checkpoint
    ``ckpt``: the measured columns of its row. A configuration is a list of overrides of
    ``--stage``, or (stage 2's hybrid) a mapping ``{overrides: [...], then_dpt: F,
    dpt_overrides: [...]}``: stage 2 for the share ``1 - F`` of the budget, then the
    path-tracing baseline for the share ``F`` from stage 2's exported grids (``init=grids``);
    its row holds the end of the second run, the sum of both runs' seconds and steps, and
    the best sigma_t over both."""
    common = [*SCENES[scene], f"callbacks.property_metrics.every_s={args.every_s}"]
    if not isinstance(config, dict):
        run, _ = train(args.stage, args.out, args.preset, [
            *common, f"init.ea_ckpt={ckpt}", f"budget_s={budget}",
            f"budget.{args.stage}.steps={MANY_STEPS}", *config])
        return run_row(run)
    if args.stage != "rte":
        raise SystemExit(f"{describe(config)}: a hybrid configuration continues stage 2 "
                         "(--stage rte).")
    if not 0 < float(config["then_dpt"]) < 1:
        raise SystemExit(f"then_dpt={config['then_dpt']}: the baseline's share of the budget, "
                         "in (0, 1).")
    tail = float(config["then_dpt"]) * budget
    first, _ = train("rte", args.out, args.preset, [
        *common, f"init.ea_ckpt={ckpt}", f"budget_s={budget - tail}",
        f"budget.rte.steps={MANY_STEPS}", *config.get("overrides", [])])
    second, _ = train("dpt", args.out, args.preset, [
        *common, "init=grids", f"init.grids={first / 'medium_grids.npz'}", f"budget_s={tail}",
        f"budget.dpt.steps={MANY_STEPS}", *config.get("dpt_overrides", [])])
    head, end = run_row(first), run_row(second)
    sigma_t = curve(first, "val/mse_sigma_t_x100") + [
        (float(head["seconds"]) + s, v) for s, v in curve(second, "val/mse_sigma_t_x100")]
    best = min(sigma_t, key=lambda p: p[1])
    return {**end, "seconds": f"{float(head['seconds']) + float(end['seconds']):.1f}",
            "steps": f"{head['steps']}+{end['steps']}", "start_sigma_t": head["start_sigma_t"],
            "best_sigma_t": f"{best[1]:.4f}", "best_at_s": f"{best[0]:.1f}"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--round", default="round1", help="a round of the configs file")
    parser.add_argument("--configs", help="comma-separated names of the round (default: all)")
    parser.add_argument("--scenes", default="default")
    parser.add_argument("--stage", default="dpt", choices=("dpt", "rte"))
    add_budget_arguments(parser, budget_s=300.0, every_s=15.0)
    parser.add_argument("--table", type=Path, help="default: docs/data/baseline_tuning.csv "
                        "(dpt) or docs/data/stage2_tuning.csv (rte)")
    parser.add_argument("--out", type=Path, default=output_dir() / "benchmarks" / "tuning")
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    table = args.table or TABLES[args.stage]
    if args.summary:
        print(summary(read_table(table)))
        return
    scenes = args.scenes.split(",")
    blind = [s for s in scenes if s not in TUNING_SCENES]
    if blind:
        parser.error(f"--scenes {','.join(blind)}: tuning runs only on the tuning scenes "
                     f"({', '.join(TUNING_SCENES)}); a blind scene may not choose a default.")
    configs_file = CONFIGS[args.stage]
    rounds = yaml.safe_load(configs_file.read_text())
    if args.round not in rounds:
        parser.error(f"--round {args.round}: {configs_file.name} has {', '.join(rounds)}.")
    configs = rounds[args.round]
    if args.configs:
        unknown = set(args.configs.split(",")) - set(configs)
        if unknown:
            parser.error(f"--configs: {', '.join(sorted(unknown))} not in {args.round}.")
        configs = {k: configs[k] for k in args.configs.split(",")}
    done = {(r["round"], r["config"], r["scene"], r["preset"], float(r["budget_s"]))
            for r in read_table(table)}
    budget = float(args.budget_s)
    for scene in scenes:
        ckpt = ea_checkpoint(scene, args.preset)
        for name, overrides in configs.items():
            key = (args.round, name, scene, args.preset, budget)
            if key in done:
                print(f"{name} on {scene}: in the table already", flush=True)
                continue
            row = {"round": args.round, "config": name, "stage": args.stage, "scene": scene,
                   "preset": args.preset, "budget_s": budget, "overrides": describe(overrides),
                   **run_config(args, scene, ckpt, budget, overrides)}
            append_rows(table, COLUMNS, [row])
            print(f"{name} on {scene}: sigma_t {row['mse_sigma_t_x100']} sigma_s "
                  f"{row['mse_sigma_s_x100']} ({row['steps']} steps)", flush=True)
    print(summary(read_table(table)))


if __name__ == "__main__":
    main()
