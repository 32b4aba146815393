"""Equal time: the differentiable path-tracing baseline (``stage=dpt``) against stage 2.

Both start from the same EA checkpoint and train for the same ``budget_s`` of training
seconds (validation not counted); then ``nrt-eval`` re-renders each result under the
novel environment and ``nrt-report`` draws both accuracy-versus-time curves in one
figure. Prints property MSE x100, novel-illumination PSNR and seconds beside the paper's
table (which used an isotropic scene and differential ratio tracking).

    python -m benchmarks.dpt_vs_rte --budget-s 300 [--ea-ckpt PATH] [--rte-run DIR]
        [--preset cpu] [--output DIR]

``--rte-run`` reuses a finished stage-2 run (e.g. the accuracy_vs_time sweep's
``ablation=base``); the baseline then gets that run's training seconds as its budget.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PAPER = {"DRT (paper)": (0.87, 4.06, 6.88, 43.3), "ours (paper)": (1.33, 1.66, 0.46, 30.5)}
MANY_STEPS = 1_000_000  # the budget stops the run


def run(cmd: list[str], out: Path) -> None:
    proc = subprocess.run(cmd, env={**os.environ, "NRT_OUTPUT_DIR": str(out)},
                          capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")


def train(out: Path, stage: str, budget: float, args, extra: list[str]) -> Path:
    data_dir = Path(os.environ.get("NRT_OUTPUT_DIR", "outputs")).resolve() / "datasets"
    run([sys.executable, "-m", "nrt.cli.train", f"stage={stage}", f"preset={args.preset}",
         f"paths.data_dir={data_dir}", "trainer.enable_progress_bar=false",
         "render.progress=false", f"budget_s={budget}", f"budget.{stage}.steps={MANY_STEPS}",
         f"init.ea_ckpt={args.ea_ckpt}", *extra], out)
    runs = sorted((out / "default" / stage).iterdir(), key=lambda p: p.stat().st_mtime)
    return runs[-1]


def evaluate(run_dir: Path, out: Path) -> dict:
    run([sys.executable, "-m", "nrt.cli.eval", f"run={run_dir}", "metrics.lpips=false",
         "relight.enabled=false"], out)
    latest = sorted(run_dir.glob("eval/*/metrics.json"))[-1]
    return json.loads(latest.read_text())["metrics"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--budget-s", type=float, default=300.0)
    parser.add_argument("--ea-ckpt", help="EA checkpoint (default: newest in outputs/)")
    parser.add_argument("--rte-run", help="reuse this finished stage-2 run folder")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--output", help="folder for the runs (default: a temporary one)")
    args = parser.parse_args()
    out = Path(args.output or tempfile.mkdtemp(prefix="nrt_dpt_vs_rte_"))
    if args.ea_ckpt is None:
        found = sorted(Path(os.environ.get("NRT_OUTPUT_DIR", "outputs")).glob(
            "default/ea/*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
        if not found:
            sys.exit("No EA checkpoint: run `nrt-train stage=ea` first or pass --ea-ckpt.")
        args.ea_ckpt = str(found[-1].resolve())
    start = time.perf_counter()
    if args.rte_run:
        rte = Path(args.rte_run)
        budget = json.loads((rte / "run.json").read_text())["final_metrics"]["time/wall_s"]
    else:
        budget = args.budget_s
        rte = train(out, "rte", budget, args, [])
    dpt = train(out, "dpt", budget, args, [])
    results = {"dpt (this run)": (dpt, evaluate(dpt, out)),
               "rte (this run)": (rte, evaluate(rte, out))}
    run([sys.executable, "-m", "nrt.cli.report", str(rte), str(dpt), "--out",
         str(out / "report")], out)
    print(f"\nEqual time: {budget:.0f} training seconds each, from {args.ea_ckpt}; "
          f"benchmark wall time {time.perf_counter() - start:.0f} s")
    print(f"{'method':<16}{'sigma_a':>9}{'sigma_s':>9}{'sigma_t':>9}{'g':>8}"
          f"{'PSNR novel':>12}{'PSNR floor':>12}{'seconds':>9}")
    for label, (run_dir, m) in results.items():
        info = json.loads((run_dir / "run.json").read_text())["final_metrics"]
        print(f"{label:<16}{m['mse_sigma_a_x100']:>9.3f}{m['mse_sigma_s_x100']:>9.3f}"
              f"{m['mse_sigma_t_x100']:>9.3f}{m.get('mse_g_x100', float('nan')):>8.3f}"
              f"{m.get('psnr_novel', m.get('psnr_seen', float('nan'))):>12.2f}"
              f"{m.get('psnr_noise_floor_novel', float('nan')):>12.2f}"
              f"{info['time/wall_s']:>9.0f}")
    for label, (a, s, t, p) in PAPER.items():
        print(f"{label:<16}{a:>9.2f}{s:>9.2f}{t:>9.2f}{'':>8}{p:>12.1f}")
    print(f"Curves: {out / 'report' / 'accuracy_vs_time.png'}; runs under {out}")


if __name__ == "__main__":
    main()
