"""A fused CPU kernel switched off and on at equal steps: stage 1 with the fused hash grid, or
stage 2 with the fused grid lookups (or with all its speed levers), per scene and seed, one
run after the other.

    python -m benchmarks.fused_equal --kernel hash_grid --scenes default,heldout2 --seeds 0,1
    python -m benchmarks.fused_equal --kernel lookups --scenes default,heldout2 --seeds 0,1
    python -m benchmarks.fused_equal --kernel rte_levers --scenes default,heldout2 --seeds 0,1

``--kernel hash_grid`` trains ``nrt-train stage=ea`` with
``model.density_field.hash_grid.fused=false`` then ``true`` and appends a row per run to
``docs/data/step_speed/fused_hash_grid_ea_equal.csv``: the held-out PSNR, the density
correlation and relative error. ``--kernel lookups`` trains ``nrt-train stage=rte`` from the
scene's EA checkpoint (the newest finished one under the output folder, else a new one; the
same for both runs) with ``fused_lookups=false`` then ``true`` and appends to
``docs/data/step_speed/fused_lookups_rte_equal.csv``: the held-out PSNR and the property
MSEs x100. ``--kernel rte_levers`` is ``lookups`` with the fused lookups and marches and
``losses.samples.uncollided_shared`` switched together (appending to
``docs/data/step_speed/rte_levers_equal.csv``): the shared refresh draws its shadow rays
differently, so there chance separates a pair by more than float rounding. All add the
steps, the training seconds and the commit; the runs go under ``<output dir>/equal``
(datasets from the shared cache). A kernel changes only the order of float sums, so what
separates a pair is chance; the seed spread of one side is the scale to judge them by.
``--sides on`` runs the fused side alone: a later change of the kernels, at the same seeds
and from the same EA checkpoints, set against the rows already in the table.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from benchmarks.common import SCENES, commit_of, ea_checkpoint, output_dir, run_finals, train

RTE_KEPT = {"psnr_heldout": "val/psnr", "mse_sigma_a_x100": "val/mse_sigma_a_x100",
            "mse_sigma_s_x100": "val/mse_sigma_s_x100", "mse_sigma_t_x100": "val/mse_sigma_t_x100"}
KERNELS = {  # name -> (stage, switches set together, table, final metrics kept: column -> key)
    "hash_grid": ("ea", ("model.density_field.hash_grid.fused",),
                  "docs/data/step_speed/fused_hash_grid_ea_equal.csv",
                  {"psnr_heldout": "val/psnr", "density_corr": "val/density_corr",
                   "density_rel_err": "val/density_rel_err"}),
    "lookups": ("rte", ("fused_lookups",), "docs/data/step_speed/fused_lookups_rte_equal.csv",
                RTE_KEPT),
    "rte_levers": ("rte", ("fused_lookups", "losses.samples.uncollided_shared"),
                   "docs/data/step_speed/rte_levers_equal.csv", RTE_KEPT),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernel", choices=sorted(KERNELS), default="hash_grid")
    parser.add_argument("--scenes", default="default", help="benchmark scenes, comma-separated")
    parser.add_argument("--seeds", default="0", help="training seeds, comma-separated")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--table", type=Path, help="default: the kernel's table")
    parser.add_argument("--sides", default="off,on",
                        help="which runs of a pair: off, on or both (a later change of the "
                             "fused side measured against the off runs already in the table)")
    args = parser.parse_args()
    sides = [{"off": False, "on": True}[side] for side in args.sides.split(",")]
    stage, switches, default_table, keep = KERNELS[args.kernel]
    table_path = args.table or Path(default_table)
    columns = ["scene", "preset", "seed", "fused", "steps", "train_s", *keep, "code"]
    out = output_dir() / "equal"
    out.mkdir(parents=True, exist_ok=True)
    code = commit_of(Path(__file__).resolve().parent.parent)
    new = not table_path.exists()
    with open(table_path, "a", newline="") as f:
        table = csv.DictWriter(f, fieldnames=columns)
        if new:
            table.writeheader()
        for scene in args.scenes.split(","):
            start = ([f"init.ea_ckpt={ea_checkpoint(scene, args.preset)}"]
                     if stage == "rte" else [])
            for seed in (int(s) for s in args.seeds.split(",")):
                for fused in sides:
                    run, _ = train(stage, out, args.preset, [
                        *SCENES[scene], *start, f"seed={seed}",
                        *(f"{switch}={str(fused).lower()}" for switch in switches)])
                    table.writerow({"scene": scene, "preset": args.preset, "seed": seed,
                                    "fused": fused, **run_finals(run, keep), "code": code})
                    f.flush()
                    print(f"{scene} seed {seed} {args.kernel}={fused}: {run}", flush=True)


if __name__ == "__main__":
    main()
