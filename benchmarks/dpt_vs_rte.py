"""Equal time: the differentiable path-tracing baseline (``stage=dpt``) against stage 2.

Both start from the same EA checkpoint and train for the same ``budget_s`` of training
seconds (validation not counted); then ``nrt-eval`` re-renders each result under the
novel environment and ``nrt-report`` draws both accuracy-versus-time curves in one
figure. Prints property MSE x100, novel-illumination PSNR and seconds beside the paper's
table (which used an isotropic scene and differential ratio tracking).

    python -m benchmarks.dpt_vs_rte --budget-s 300 [--ea-ckpt PATH] [--rte-run DIR]
        [--scene default] [--preset cpu] [--output DIR]

``--rte-run`` reuses a finished stage-2 run (e.g. the accuracy_vs_time sweep's
``ablation=base``); the baseline then gets that run's training seconds as its budget, and
its scene and EA checkpoint unless ``--scene`` / ``--ea-ckpt`` say otherwise.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.common import (
    newest_checkpoint,
    output_dir,
    run_cli,
    scene_dataset,
    series,
    train,
)

PAPER = {"DRT (paper)": (0.87, 4.06, 6.88, 43.3), "ours (paper)": (1.33, 1.66, 0.46, 30.5)}
MANY_STEPS = 1_000_000  # the budget stops the run


def train_for(out: Path, stage: str, budget: float, args) -> Path:
    """``nrt-train stage=<stage>`` from ``args.ea_ckpt`` for ``budget`` training seconds
    under ``out``; its run folder."""
    return train(stage, out, args.preset, [f"budget_s={budget}",
                                           f"budget.{stage}.steps={MANY_STEPS}",
                                           f"init.ea_ckpt={args.ea_ckpt}",
                                           f"scene={args.scene}"])[0]


def reused_start(rte_run: Path) -> tuple[str, str | None]:
    """The scene and the EA checkpoint a finished stage-2 run started from (its run.json)."""
    info = json.loads((rte_run / "run.json").read_text())
    return info.get("scene", "default"), info.get("ea_ckpt")


def evaluate(run_dir: Path, out: Path) -> dict:
    run_cli("eval", [f"run={run_dir}", "metrics.lpips=false", "relight.enabled=false"], out)
    latest = sorted(run_dir.glob("eval/*/metrics.json"))[-1]
    return json.loads(latest.read_text())["metrics"]


def steps_taken(run_dir: Path) -> int | None:
    """Training steps of a run (the last logged step of its CSV log; None without one)."""
    if not (run_dir / "csv" / "metrics.csv").is_file():
        return None
    return int(max(series(run_dir, "step"), default=0)) or None


def learns_g(run_dir: Path) -> bool:
    """Whether the run's g is learned (stage 2 always; the baseline unless ``model.phase_g``
    fixes it)."""
    config = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())
    return config["stage"]["name"] != "dpt" or config["model"].get("phase_g") is None


def print_table(results: dict[str, tuple[Path, dict]]) -> None:
    """Start (step 0, from the run's property curves) and end (nrt-eval) of each run."""
    from nrt.evaluation.report import read_run

    print(f"{'method':<22}{'sigma_a':>9}{'sigma_s':>9}{'sigma_t':>9}{'g':>8}"
          f"{'PSNR novel':>12}{'PSNR floor':>12}{'seconds':>9}{'steps':>7}{'s/step':>8}")
    nan = float("nan")
    for label, (run_dir, m) in results.items():
        curves = read_run(run_dir).curves
        first = {k: curves[f"val/mse_{k}_x100"][1][0] if f"val/mse_{k}_x100" in curves else nan
                 for k in ("sigma_a", "sigma_s", "sigma_t", "g")}
        g_start = f"{first['g']:>8.3f}" if learns_g(run_dir) else f"{'':>8}"
        print(f"{label + ' start':<22}{first['sigma_a']:>9.3f}{first['sigma_s']:>9.3f}"
              f"{first['sigma_t']:>9.3f}{g_start}{'':>12}{'':>12}{0:>9}")
        seen = "psnr_novel" not in m  # a dataset with one environment: novel views only
        psnr = m.get("psnr_seen" if seen else "psnr_novel", nan)
        floor = m.get("psnr_noise_floor_seen" if seen else "psnr_noise_floor_novel", nan)
        g_end = f"{m.get('mse_g_x100', nan):>8.3f}" if learns_g(run_dir) else f"{'fixed':>8}"
        seconds = json.loads((run_dir / "run.json").read_text())["final_metrics"]["time/wall_s"]
        steps = steps_taken(run_dir)
        per_step = f"{seconds / steps:>8.2f}" if steps else f"{'-':>8}"
        print(f"{label + ' end':<22}{m['mse_sigma_a_x100']:>9.3f}{m['mse_sigma_s_x100']:>9.3f}"
              f"{m['mse_sigma_t_x100']:>9.3f}{g_end}{psnr:>11.2f}{'*' if seen else ' '}"
              f"{floor:>12.2f}{seconds:>9.0f}{steps or '-':>7}{per_step}")
    for label, (a, s, t, p) in PAPER.items():
        print(f"{label:<22}{a:>9.2f}{s:>9.2f}{t:>9.2f}{'':>8}{p:>11.1f}")
    print("g 'fixed': the baseline's g given by model.phase_g (not scored). *: no novel "
          "environment in the dataset, PSNR of the held-out views under the training one.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--budget-s", type=float, default=300.0)
    parser.add_argument("--ea-ckpt", help="EA checkpoint (default: newest in outputs/)")
    parser.add_argument("--rte-run", help="reuse this finished stage-2 run folder")
    parser.add_argument("--scene", help="scene config (default: the --rte-run's, else default)")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--output", help="folder for the runs (default: a temporary one)")
    args = parser.parse_args()
    out = Path(args.output or tempfile.mkdtemp(prefix="nrt_dpt_vs_rte_"))
    if args.rte_run and not (Path(args.rte_run) / "run.json").is_file():
        parser.error(f"--rte-run {args.rte_run}: no run.json there; pass a finished stage-2 run "
                     "folder (outputs/<scene>/rte/<time>).")
    scene, ea_ckpt = reused_start(Path(args.rte_run)) if args.rte_run else ("default", None)
    args.scene = args.scene or scene
    args.ea_ckpt = args.ea_ckpt or ea_ckpt
    if args.ea_ckpt is None:
        found = newest_checkpoint(args.scene, scene_dataset(args.preset, [f"scene={args.scene}"]))
        if found is None:
            parser.error(f"no EA checkpoint of scene '{args.scene}' under {output_dir()}: run "
                         f"`nrt-train stage=ea scene={args.scene}` first or pass --ea-ckpt.")
        args.ea_ckpt = str(found)
    start = time.perf_counter()
    if args.rte_run:
        rte = Path(args.rte_run)
        budget = json.loads((rte / "run.json").read_text())["final_metrics"]["time/wall_s"]
    else:
        budget = args.budget_s
        rte = train_for(out, "rte", budget, args)
    dpt = train_for(out, "dpt", budget, args)
    results = {"dpt (this run)": (dpt, evaluate(dpt, out)),
               "rte (this run)": (rte, evaluate(rte, out))}
    run_cli("report", [str(rte), str(dpt), "--out", str(out / "report")], out)
    print(f"\nEqual time on scene '{args.scene}': {budget:.0f} training seconds each, from "
          f"{args.ea_ckpt}; "
          f"benchmark wall time {time.perf_counter() - start:.0f} s")
    print_table(results)
    print(f"Curves: {out / 'report' / 'accuracy_vs_time.png'}; runs under {out}")


if __name__ == "__main__":
    main()
