"""Stage 2 at the preset's defaults on several scenes: does the medium improve on its EA start?

For each scene: the EA checkpoint (``--ea NAME=PATH``, else the newest EA run of that scene
under ``outputs/``, else ``nrt-train stage=ea`` is run first), then ``nrt-train stage=rte``
at the preset's defaults through the real CLI in ``--out``. Prints one row per scene: the
property MSEs x100 at step 0 and at the end, the end/start ratios, the held-out PSNR of the
photo objective's image, training seconds and steps. Every scene is reported, none chosen.

    python -m benchmarks.stage2_scenes [--scenes default,default_seed1,...] [--ea NAME=PATH ...]
        [--preset cpu] [--data OVERRIDE ...] [--out DIR] [override ...]

``override``s go to stage 2 only; ``--data`` overrides (``--data scene.spp=512``) change the
photos, so they go to the EA run trained first as well: give them with a new
``NRT_OUTPUT_DIR``, whose newest EA runs are then those of the same photos.

Scenes: ``default`` (the settings were chosen on it), ``default_seed1..3`` (the default
scene drawn from other seeds), ``varying_g`` (a g field), ``heldout``, ``heldout2`` and
``heldout3`` (explicit elements lists, each written once and never tuned on; the second
after the extinction prior was chosen, the third after the total-variation prior).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.common import SCENES, ea_checkpoint, output_dir, series, train

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--ea", action="append", default=[], help="NAME=path/to/last.ckpt")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--data", action="append", default=[],
                        help="an override of the scene's photos (scene.spp=512), for both stages")
    parser.add_argument("--out", type=Path, default=output_dir() / "benchmarks" / "stage2")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for stage 2")
    args = parser.parse_args()
    given = dict(item.split("=", 1) for item in args.ea)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.scenes.split(","):
        scene = [*SCENES[name], *args.data]
        ckpt = given.get(name) or ea_checkpoint(name, args.preset, scene)
        run, _ = train("rte", args.out, args.preset,
                       [*scene, f"init.ea_ckpt={ckpt}", *args.overrides])
        mse = {k: series(run, f"val/mse_{k}_x100") for k in PROPERTIES}
        rows.append((name, mse, series(run, "val/psnr")[-1], series(run, "time/wall_s")[-1],
                     int(max(series(run, "step"))) + 1))
        print(f"{name}: {run}", flush=True)
    print("\n| scene | " + " | ".join(f"{k} start -> end (ratio)" for k in PROPERTIES)
          + " | PSNR | seconds | steps |")
    print("|---|" + "---:|" * (len(PROPERTIES) + 3))
    for name, mse, psnr, seconds, steps in rows:
        cells = [f"{v[0]:.3f} -> {v[-1]:.3f} ({v[-1] / v[0]:.2f})" if v else "-"
                 for v in mse.values()]
        print(f"| {name} | " + " | ".join(cells) + f" | {psnr:.2f} | {seconds:.0f} | {steps} |")


if __name__ == "__main__":
    main()
