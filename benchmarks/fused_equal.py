"""Stage 1 with the PyTorch hash grid and with the fused one, at equal steps: held-out PSNR,
density correlation and training seconds per scene and seed, one run after the other.

    python -m benchmarks.fused_equal --scenes default,heldout2 --seeds 0,1 \
        [--preset cpu] [--table docs/data/step_speed/fused_hash_grid_ea_equal.csv]

Each (scene, seed) trains ``nrt-train stage=ea`` twice, ``hash_grid.fused=false`` then
``true``, under ``<output dir>/equal`` (datasets from the shared cache), and appends one row
per run to the table: ``val/psnr`` (held-out views), ``val/density_corr`` and
``val/density_rel_err`` from the run's ``run.json``, and ``time/wall_s``, the training's
seconds. The pairs differ only in the hash grid's order of sums (docs/conventions.md), so
what separates them is chance; the seed spread of one side is the scale to judge them by.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from benchmarks.common import SCENES, commit_of, output_dir, train
from nrt.run_dirs import read_run_info

COLUMNS = ("scene", "preset", "seed", "fused", "steps", "train_s", "psnr_heldout",
           "density_corr", "density_rel_err", "code")
"""The table's columns; ``fused`` is the switch of the row's run."""


def row(run: Path, scene: str, preset: str, seed: int, fused: bool, code: str) -> dict:
    """The table's row of a finished stage-1 run."""
    info = read_run_info(run)
    final = info["final_metrics"]
    return {"scene": scene, "preset": preset, "seed": seed, "fused": fused,
            "steps": info["finished_step"], "train_s": round(final["time/wall_s"], 1),
            "psnr_heldout": round(final["val/psnr"], 3),
            "density_corr": round(final["val/density_corr"], 4),
            "density_rel_err": round(final["val/density_rel_err"], 4), "code": code}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="default", help="benchmark scenes, comma-separated")
    parser.add_argument("--seeds", default="0", help="training seeds, comma-separated")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--table", type=Path,
                        default=Path("docs/data/step_speed/fused_hash_grid_ea_equal.csv"))
    args = parser.parse_args()
    out = output_dir() / "equal"
    out.mkdir(parents=True, exist_ok=True)
    code = commit_of(Path(__file__).resolve().parent.parent)
    new = not args.table.exists()
    with open(args.table, "a", newline="") as f:
        table = csv.DictWriter(f, fieldnames=COLUMNS)
        if new:
            table.writeheader()
        for scene in args.scenes.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                for fused in (False, True):
                    run, _ = train("ea", out, args.preset, [
                        *SCENES[scene], f"seed={seed}",
                        f"model.density_field.hash_grid.fused={str(fused).lower()}"])
                    table.writerow(row(run, scene, args.preset, seed, fused, code))
                    f.flush()
                    print(f"{scene} seed {seed} fused={fused}: {run}", flush=True)


if __name__ == "__main__":
    main()
