"""The light field alone: forward mode (the true medium) of both stage-2 formulations.

Runs ``nrt-train stage=forward`` through the real CLI, once with the default (split)
formulation and once with ``experiment=rte_paper``, on the same dataset, one after the
other, and prints at every validation the training seconds, the held-out PSNR of the
image each renders (``val/psnr``) and of the light field alone where the rays leave the
box (``val/psnr_exit``), beside the no-scattering prediction ``T E(v)``. How fast and how
well the light field converges before any medium is learned.

    python -m benchmarks.stage2_forward [--preset tiny] [--steps 600] [override ...]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from benchmarks.common import output_dir, series, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    print(f"forward mode, preset={args.preset}, datasets under {output_dir() / 'datasets'}")
    with tempfile.TemporaryDirectory() as tmp:
        for label, extra in (("split (default)", []), ("paper", ["experiment=rte_paper"])):
            run, _ = train("forward", Path(tmp), args.preset,
                           [f"budget.rte.steps={args.steps}",
                            f"budget.val_every={args.steps // 6}", *extra, *args.overrides])
            seconds, psnr, exit_ = (series(run, k) for k in ("time/wall_s", "val/psnr",
                                                               "val/psnr_exit"))
            steps = series(run, "step")
            print(f"\n== {label}: T E(v) {series(run, 'val/psnr_transmitted_only')[-1]:.2f} dB, "
                  f"background only {series(run, 'val/psnr_background_only')[-1]:.2f} dB")
            print(f"{'validation':>10} {'psnr':>7} {'exit':>7}")
            for i, (p, e) in enumerate(zip(psnr, exit_, strict=True)):
                print(f"{i + 1:>10} {p:7.2f} {e:7.2f}")
            print(f"{int(max(steps)) + 1} steps in {seconds[-1]:.0f} training seconds")


if __name__ == "__main__":
    main()
