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
import tempfile
from pathlib import Path

from benchmarks.common import metric_rows, series, train

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")


def hms(seconds: float) -> str:
    s = int(seconds)
    return f"00:{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def train_for(out: Path, stage: str, seconds: float, overrides: list[str]) -> tuple[Path, float]:
    """One ``nrt-train`` run (``preset=cpu``, CSV log) of at most ``seconds`` under ``out``;
    its run folder and wall time (s)."""
    return train(stage, out, "cpu", [f"+trainer.max_time={hms(seconds)}", *overrides],
                 logger="csv")


def report(label: str, run: Path, wall: float) -> None:
    rows = metric_rows(run)
    steps = int(max(float(r["step"]) for r in rows)) + 1
    print(f"\n== stage 2: {label}  ({steps} steps, {wall:.0f} s wall incl. start-up, "
          f"{series(run, 'time/wall_s')[-1]:.0f} s training)")
    for key in PROPERTIES:
        vals = series(run, f"val/mse_{key}_x100")
        if vals:
            print(f"  MSE x100 {key:8s} start {vals[0]:8.3f}  end {vals[-1]:8.3f}")
    for key in ("psnr", "psnr_exit", "psnr_background_only", "psnr_transmitted_only"):
        vals = series(run, f"val/{key}")
        if vals:
            print(f"  held-out {key:22s} {vals[-1]:6.2f} dB")
    names = sorted({k[len("time/step_"):-2] for r in rows for k in r
                    if k.startswith("time/step_") and r[k]})
    times = {k: series(run, f"time/step_{k}_s") for k in names}
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
        ea_run, ea_wall = train_for(out, "ea", args.ea_seconds, scene)
        print(f"== stage 1 (EA): {int(max(series(ea_run, 'step'))) + 1} steps, "
              f"{ea_wall:.0f} s wall; held-out PSNR {series(ea_run, 'val/psnr')[-1]:.2f} dB, "
              f"density corr {series(ea_run, 'val/density_corr')[-1]:.3f}")
        variants = [("full gradients", [])]
        if args.compare_detach:
            variants.append(("detached in-scattering", ["losses.detach_inscatter=true"]))
        for label, extra in variants:
            run, wall = train_for(out, "rte", args.rte_seconds, scene + extra + args.overrides)
            report(label, run, wall)


if __name__ == "__main__":
    main()
