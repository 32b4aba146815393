"""The full two-stage pipeline (``stage=ea`` then ``stage=rte``) at the ``cpu`` preset.

Runs the real CLI in a temporary output folder (the dataset is shared with ``outputs/``),
each stage under a wall-clock budget, and prints for every stage-2 variant: the property
MSEs (x10^2) at the start and the end, held-out PSNR of the VRE image and of the light
field at the box exit (with the background-only and no-scattering baselines), time per
step split by objective, steps and total time. ``--compare-detach`` (a knob of the
paper's formulation: pass ``experiment=rte_paper`` too) trains stage 2 twice from the same
EA checkpoint, with and without gradients through the in-scattered radiance, side by side
in one run.

    python -m benchmarks.rte_cpu --ea-seconds 600 --rte-seconds 900 [--compare-detach]
        [--scene default] [override ...]
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")


def hms(seconds: float) -> str:
    s = int(seconds)
    return f"00:{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def train(out: Path, stage: str, seconds: float, overrides: list[str]) -> tuple[Path, float]:
    """One ``nrt-train`` run under ``out``; its run folder and wall time (s)."""
    data_dir = Path(os.environ.get("NRT_OUTPUT_DIR", "outputs")).resolve() / "datasets"
    cmd = [sys.executable, "-m", "nrt.cli.train", f"stage={stage}", "preset=cpu", "logger=csv",
           f"paths.data_dir={data_dir}", "trainer.enable_progress_bar=false",
           f"+trainer.max_time={hms(seconds)}", *overrides]
    start = time.perf_counter()
    proc = subprocess.run(cmd, env={**os.environ, "NRT_OUTPUT_DIR": str(out)},
                          capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    runs = sorted((out / "default" / stage).iterdir(), key=lambda p: p.stat().st_mtime)
    return runs[-1], wall


def metrics(run: Path) -> list[dict]:
    with open(run / "csv" / "metrics.csv") as f:
        return list(csv.DictReader(f))


def series(rows: list[dict], key: str) -> list[float]:
    return [float(r[key]) for r in rows if r.get(key)]


def report(label: str, run: Path, wall: float) -> None:
    rows = metrics(run)
    steps = int(max(float(r["step"]) for r in rows)) + 1
    print(f"\n== stage 2: {label}  ({steps} steps, {wall:.0f} s wall incl. start-up, "
          f"{series(rows, 'time/wall_s')[-1]:.0f} s training)")
    for key in PROPERTIES:
        vals = series(rows, f"val/mse_{key}_x100")
        if vals:
            print(f"  MSE x100 {key:8s} start {vals[0]:8.3f}  end {vals[-1]:8.3f}")
    for key in ("psnr", "psnr_exit", "psnr_background_only", "psnr_transmitted_only"):
        vals = series(rows, f"val/{key}")
        if vals:
            print(f"  held-out {key:22s} {vals[-1]:6.2f} dB")
    names = sorted({k[len("time/step_"):-2] for r in rows for k in r
                    if k.startswith("time/step_") and r[k]})
    times = {k: series(rows, f"time/step_{k}_s") for k in names}
    means = {k: sum(v) / len(v) for k, v in times.items() if v}
    total = sum(means.values())
    split = ", ".join(f"{k} {v * 1e3:.0f} ms ({100 * v / total:.0f}%)" for k, v in means.items())
    print(f"  time per step {total * 1e3:.0f} ms: {split}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ea-seconds", type=float, default=600.0)
    parser.add_argument("--rte-seconds", type=float, default=900.0)
    parser.add_argument("--compare-detach", action="store_true")
    parser.add_argument("--scene", default="default")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for stage 2")
    args = parser.parse_args()
    scene = [f"scene={args.scene}"]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        ea_run, ea_wall = train(out, "ea", args.ea_seconds, scene)
        ea_rows = metrics(ea_run)
        print(f"== stage 1 (EA): {int(max(float(r['step']) for r in ea_rows)) + 1} steps, "
              f"{ea_wall:.0f} s wall; held-out PSNR {series(ea_rows, 'val/psnr')[-1]:.2f} dB, "
              f"density corr {series(ea_rows, 'val/density_corr')[-1]:.3f}")
        variants = [("full gradients", [])]
        if args.compare_detach:
            variants.append(("detached in-scattering", ["losses.detach_inscatter=true"]))
        for label, extra in variants:
            run, wall = train(out, "rte", args.rte_seconds, scene + extra + args.overrides)
            report(label, run, wall)


if __name__ == "__main__":
    main()
